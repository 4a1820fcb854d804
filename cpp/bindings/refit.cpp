// Private binding of the relaxed group-lasso refit (public API: bubble_rt.estimation.estimator).
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <string>

#include "errors.h"
#include "green_membrane.h"
#include "membrane.h"
#include "nonlinear_refit.h"
#include "support_refit.h"

namespace py = pybind11;
using bubble::RowMatrixX3d;

namespace {
using ArrD = py::array_t<double, py::array::c_style>;
using ArrI = py::array_t<int, py::array::c_style>;
using ArrB = py::array_t<bool, py::array::c_style>;
}  // namespace

void bind_refit(py::module_& m) {
  using R = bubble::SupportRefit;
  py::class_<R>(m, "_SupportRefit")
      .def(py::init([](const bubble::MembraneModel& model, const ArrI& boundary) {
             bubble::require(boundary.ndim() == 1, "boundary must be 1-D");
             Eigen::Map<const Eigen::VectorXi> b(boundary.data(), boundary.shape(0));
             py::gil_scoped_release release;
             return std::make_unique<R>(model.stiffness(), model.area_normals(), b);
           }),
           py::arg("model"), py::arg("boundary").noconvert())
      .def(
          "refit",
          [](const R& self, const ArrD& u, double dp, const ArrB& support) {
            bubble::require(u.ndim() == 2 && u.shape(1) == 3, "U must be N x 3");
            bubble::require(support.ndim() == 1, "support must be 1-D");
            Eigen::Map<const RowMatrixX3d> U(u.data(), u.shape(0), 3);
            Eigen::Map<const Eigen::Matrix<bool, Eigen::Dynamic, 1>> s(support.data(),
                                                                       support.shape(0));
            py::gil_scoped_release release;
            return self.refit(U, dp, s);
          },
          py::arg("U").noconvert(), py::arg("dp"), py::arg("support").noconvert())
      .def_property_readonly("n_nodes", &R::n_nodes)
      .def_property_readonly("setup_time_ms", &R::setup_time_ms);

  using NR = bubble::NonlinearRefit;
  py::class_<NR>(m, "_NonlinearRefit")
      .def(py::init([](const R& refit, const bubble::GreenMembrane& green) {
             return std::make_unique<NR>(refit, green);
           }),
           py::arg("refit"), py::arg("green"), py::keep_alive<1, 2>(), py::keep_alive<1, 3>())
      .def(
          "refit",
          [](const NR& self, const ArrD& u, double dp, const ArrB& support, int iterations) {
            bubble::require(u.ndim() == 2 && u.shape(1) == 3, "U must be N x 3");
            bubble::require(support.ndim() == 1, "support must be 1-D");
            Eigen::Map<const RowMatrixX3d> U(u.data(), u.shape(0), 3);
            Eigen::Map<const Eigen::Matrix<bool, Eigen::Dynamic, 1>> s(support.data(),
                                                                       support.shape(0));
            NR::Result r;
            {
              py::gil_scoped_release release;
              r = self.refit(U, dp, s, iterations);
            }
            return py::make_tuple(py::cast(std::move(r.linear)), py::cast(std::move(r.nonlinear)),
                                  r.steps);
          },
          py::arg("U").noconvert(), py::arg("dp"), py::arg("support").noconvert(),
          py::arg("iterations"))
      .def_property_readonly("n_nodes", &NR::n_nodes);
}
