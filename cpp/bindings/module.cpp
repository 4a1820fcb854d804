// The one pybind11 module. Each concept binds itself in cpp/bindings/<concept>.cpp.
#include <pybind11/pybind11.h>

#include "dense_cholesky.h"
#include "errors.h"

namespace py = pybind11;

void bind_membrane(py::module_& m);
void bind_green_membrane(py::module_& m);
void bind_solver(py::module_& m);
void bind_refit(py::module_& m);
void bind_deformation(py::module_& m);
void bind_sim(py::module_& m);
void bind_render(py::module_& m);
void bind_contact(py::module_& m);

PYBIND11_MODULE(_core, m) {
  m.doc() = "bubble_rt C++ core (private: use the bubble_rt Python API)";
  // Registered once, before any binding can throw it: every binding's bad input becomes
  // _core.InputError, a ValueError.
  py::register_exception<bubble::InputError>(m, "InputError", PyExc_ValueError);
  bubble::use_single_threaded_blas();
  bind_membrane(m);
  bind_green_membrane(m);
  bind_solver(m);
  bind_refit(m);
  bind_deformation(m);
  bind_sim(m);
  bind_render(m);
  bind_contact(m);
}
