// Private binding of the ADMM group-lasso solver (public API: bubble_rt.estimation.solver).
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <memory>

#include "errors.h"
#include "group_lasso.h"
#include "membrane.h"
#include "numpy_views.h"

namespace py = pybind11;
using bubble::bindings::ArrD;
using bubble::bindings::ArrI;
using bubble::bindings::map_n3;

void bind_solver(py::module_& m) {
  using S = bubble::SolverSettings;
  py::class_<S>(m, "_SolverSettings")
      .def(py::init<>())
      .def_readwrite("rho", &S::rho)
      .def_readwrite("sigma", &S::sigma)
      .def_readwrite("alpha", &S::alpha)
      .def_readwrite("adaptive_rho", &S::adaptive_rho)
      .def_readwrite("adaptive_rho_tolerance", &S::adaptive_rho_tolerance)
      .def_readwrite("adaptive_rho_interval", &S::adaptive_rho_interval)
      .def_readwrite("eps_abs", &S::eps_abs)
      .def_readwrite("eps_rel", &S::eps_rel)
      .def_readwrite("max_iter", &S::max_iter)
      .def_readwrite("check_interval", &S::check_interval)
      .def_readwrite("time_limit", &S::time_limit)
      .def_readwrite("scaling_iter", &S::scaling_iter)
      .def_readwrite("warm_start", &S::warm_start)
      .def_readwrite("anderson_memory", &S::anderson_memory)
      .def("validate", &S::validate);

  using I = bubble::SolverInfo;
  py::class_<I>(m, "_SolverInfo")
      .def_property_readonly("status", [](const I& i) { return bubble::to_string(i.status); })
      .def_readonly("iterations", &I::iterations)
      .def_readonly("primal_residual", &I::primal_residual)
      .def_readonly("dual_residual", &I::dual_residual)
      .def_readonly("objective", &I::objective)
      .def_readonly("duality_gap", &I::duality_gap)
      .def_readonly("rho", &I::rho)
      .def_readonly("factorizations", &I::factorizations)
      .def_readonly("setup_time_ms", &I::setup_time_ms)
      .def_readonly("solve_time_ms", &I::solve_time_ms);

  using G = bubble::GroupLassoSolver;
  py::class_<G>(m, "_GroupLassoSolver")
      .def(py::init([](const bubble::MembraneModel& model, const ArrI& boundary, double k_f,
                       double k_u, const S& settings) {
             bubble::require(boundary.ndim() == 1, "boundary must be 1-D");
             Eigen::Map<const Eigen::VectorXi> b(boundary.data(), boundary.shape(0));
             py::gil_scoped_release release;
             return std::make_unique<G>(model.stiffness(), model.area_normals(), b, k_f, k_u,
                                        settings);
           }),
           py::arg("model"), py::arg("boundary").noconvert(), py::arg("k_f"), py::arg("k_u"),
           py::arg("settings"))
      .def("set_weights", &G::set_weights, py::arg("k_f"), py::arg("k_u"),
           py::call_guard<py::gil_scoped_release>())
      .def("set_settings", &G::set_settings, py::arg("settings"),
           py::call_guard<py::gil_scoped_release>())
      .def(
          "update",
          [](G& self, const ArrD& u, double dp) {
            auto U = map_n3(u, "U");
            py::gil_scoped_release release;
            self.update(U, dp);
          },
          py::arg("U").noconvert(), py::arg("dp"))
      .def(
          "warm_start",
          [](G& self, const ArrD& v, const ArrD& y) {
            auto V = map_n3(v, "primal");
            auto Y = map_n3(y, "dual");
            py::gil_scoped_release release;
            self.warm_start(V, Y);
          },
          py::arg("primal").noconvert(), py::arg("dual").noconvert())
      .def("cold_start", &G::cold_start)
      .def("solve",
           [](G& self) {
             bubble::SolverResult r;
             {
               py::gil_scoped_release release;
               r = self.solve();
             }
             return py::make_tuple(r.dU, r.dual, r.info);
           })
      .def_property_readonly("n_nodes", &G::n_nodes)
      .def_property_readonly("setup_time_ms", &G::setup_time_ms);
}
