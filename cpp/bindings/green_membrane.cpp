// Private binding of the nonlinear membrane's forces (reference definition and public API:
// bubble_rt.estimation.membrane.GreenMembrane).
#include "green_membrane.h"

#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "errors.h"
#include "numpy_views.h"

namespace py = pybind11;
using bubble::RowMatrixX3i;
using bubble::bindings::ArrD;
using bubble::bindings::ArrI;
using bubble::bindings::map_n3;

void bind_green_membrane(py::module_& m) {
  using G = bubble::GreenMembrane;
  py::class_<G>(m, "_GreenMembrane")
      .def(py::init([](const ArrD& v, const ArrI& t, double E, double nu, double th, double tension,
                       double p0) {
             auto V = map_n3(v, "vertices");
             bubble::require(t.ndim() == 2 && t.shape(1) == 3, "triangles must be T x 3");
             Eigen::Map<const RowMatrixX3i> T(t.data(), t.shape(0), 3);
             py::gil_scoped_release release;
             return std::make_unique<G>(V, T, E, nu, th, tension, p0);
           }),
           py::arg("vertices").noconvert(), py::arg("triangles").noconvert(), py::arg("E"),
           py::arg("nu"), py::arg("thickness"), py::arg("tension"), py::arg("p0"))
      .def_property_readonly("n_nodes", &G::n_nodes)
      .def(
          "external_forces",
          [](const G& self, const ArrD& u, double dp) {
            auto U = map_n3(u, "U");
            py::gil_scoped_release release;
            return self.external_forces(U, dp);
          },
          py::arg("U").noconvert(), py::arg("dp"));
}
