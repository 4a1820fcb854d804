// Private binding of the simulator's membrane system (use bubble_rt.sim.physics).
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <utility>

#include "errors.h"
#include "sim_membrane.h"

namespace py = pybind11;
using bubble::SimMembrane;
using bubble::SimRef3;
using bubble::SimRef9;
using bubble::SimRowMatrixX3d;
using bubble::SimRowMatrixX3i;
using bubble::SimRowMatrixX9d;

void bind_sim(py::module_& m) {
  py::class_<SimMembrane>(m, "_SimMembrane")
      .def(py::init<const SimRowMatrixX3d&, const SimRowMatrixX3i&, const Eigen::VectorXi&,
                    double>(),
           py::arg("rest"), py::arg("triangles"), py::arg("fixed"), py::arg("mu_t"))
      .def_property_readonly("n_free_dofs", &SimMembrane::n_free_dofs)
      .def_property_readonly("nnz", &SimMembrane::nnz)
      .def(
          "energy",
          [](const SimMembrane& s, const SimRef3& x) {
            py::gil_scoped_release nogil;
            return s.energy(x, nullptr);
          },
          py::arg("x"))
      .def(
          "energy_grad",
          [](const SimMembrane& s, const SimRef3& x) {
            SimRowMatrixX3d g;
            double e;
            {
              py::gil_scoped_release nogil;
              e = s.energy(x, &g);
            }
            return std::make_pair(e, g);
          },
          py::arg("x"))
      .def(
          "volume_grad",
          [](const SimMembrane& s, const SimRef3& x) {
            SimRowMatrixX3d g;
            double v;
            {
              py::gil_scoped_release nogil;
              v = s.volume(x, &g);
            }
            return std::make_pair(v, g);
          },
          py::arg("x"))
      .def(
          "factorize",
          [](SimMembrane& s, const SimRef3& x, double volume_scale, const SimRef9& blocks,
             double shift, bool project) {
            py::gil_scoped_release nogil;
            return s.factorize(x, volume_scale, blocks, shift, project);
          },
          py::arg("x"), py::arg("volume_scale"), py::arg("blocks"), py::arg("shift"),
          py::arg("project"))
      .def(
          "assemble",
          [](SimMembrane& s, const SimRef3& x, double volume_scale, const SimRef9& blocks,
             double shift, bool project) {
            py::gil_scoped_release nogil;
            s.assemble(x, volume_scale, blocks, shift, project);
          },
          py::arg("x"), py::arg("volume_scale"), py::arg("blocks"), py::arg("shift"),
          py::arg("project"))
      .def("factorize_assembled",
           [](SimMembrane& s) {
             py::gil_scoped_release nogil;
             return s.factorize_assembled();
           })
      .def(
          "multiply",
          [](const SimMembrane& s, const SimRef3& v) {
            py::gil_scoped_release nogil;
            return s.multiply(v);
          },
          py::arg("v"))
      .def_property_readonly("factor_nnz", &SimMembrane::factor_nnz)
      .def("nonpositive_pivots", &SimMembrane::nonpositive_pivots)
      .def(
          "solve",
          [](const SimMembrane& s, const SimRef3& rhs) {
            py::gil_scoped_release nogil;
            return s.solve(rhs);
          },
          py::arg("rhs"));
}
