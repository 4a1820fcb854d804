// Private binding of the membrane model (public API: bubble_rt.estimation.membrane).
#include "membrane.h"

#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "errors.h"
#include "numpy_views.h"

namespace py = pybind11;
using bubble::RowMatrixX3i;
using bubble::bindings::ArrB;
using bubble::bindings::ArrD;
using bubble::bindings::ArrI;
using bubble::bindings::map_n;
using bubble::bindings::map_n3;

void bind_membrane(py::module_& m) {
  py::class_<bubble::MembraneModel>(m, "_Membrane")
      .def(py::init([](const ArrD& v, const ArrI& t, double E, double nu, double th) {
             auto V = map_n3(v, "vertices");
             bubble::require(t.ndim() == 2 && t.shape(1) == 3, "triangles must be T x 3");
             Eigen::Map<const RowMatrixX3i> T(t.data(), t.shape(0), 3);
             py::gil_scoped_release release;
             return bubble::MembraneModel(V, T, E, nu, th);
           }),
           py::arg("vertices").noconvert(), py::arg("triangles").noconvert(), py::arg("E"),
           py::arg("nu"), py::arg("thickness"))
      .def_property_readonly("n_nodes", &bubble::MembraneModel::n_nodes)
      .def("stiffness_csr",
           [](const bubble::MembraneModel& self) {
             return Eigen::SparseMatrix<double, Eigen::RowMajor>(self.stiffness());
           })
      .def(
          "add_stiffness",
          [](bubble::MembraneModel& self, const bubble::SparseMatrixd& dK) {
            py::gil_scoped_release release;
            self.add_stiffness(dK);
          },
          py::arg("dK"))
      .def_property_readonly("areas", &bubble::MembraneModel::areas)
      .def_property_readonly("normals", &bubble::MembraneModel::normals)
      .def_property_readonly("area_normals", &bubble::MembraneModel::area_normals)
      .def(
          "external_forces",
          [](const bubble::MembraneModel& self, const ArrD& u, double dp) {
            auto U = map_n3(u, "U");
            py::gil_scoped_release release;
            return self.external_forces(U, dp);
          },
          py::arg("U").noconvert(), py::arg("dp"));

  m.def(
      "_normal_pressure",
      [](const ArrD& f, const ArrD& a, const ArrD& n) {
        return bubble::normal_pressure(map_n3(f, "forces"), map_n(a, "areas"),
                                       map_n3(n, "normals"));
      },
      py::arg("forces").noconvert(), py::arg("areas").noconvert(), py::arg("normals").noconvert());
  m.def(
      "_contact_mask",
      [](const ArrD& p, const ArrD& a, double k_const, double k_linear) {
        return bubble::contact_mask(map_n(p, "pressure"), map_n(a, "areas"), k_const, k_linear);
      },
      py::arg("pressure").noconvert(), py::arg("areas").noconvert(), py::arg("k_const"),
      py::arg("k_linear"));
  m.def(
      "_net_force",
      [](const ArrD& f, const ArrB& interior) {
        bubble::require(interior.ndim() == 1, "interior must be 1-D");
        Eigen::Map<const Eigen::Matrix<bool, Eigen::Dynamic, 1>> mask(interior.data(),
                                                                      interior.shape(0));
        return bubble::net_force(map_n3(f, "forces"), mask);
      },
      py::arg("forces").noconvert(), py::arg("interior").noconvert());
}
