// Private binding of the contact rule's load regions (public API:
// bubble_rt.estimation.estimator.load_regions).
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <limits>

#include "load_hulls.h"
#include "load_regions.h"
#include "numpy_views.h"

namespace py = pybind11;
using bubble::bindings::ArrB;
using bubble::bindings::ArrD;
using bubble::bindings::ArrI;

void bind_contact(py::module_& m) {
  m.def(
      "_load_regions",
      [](const ArrD& pd, const ArrB& support, const ArrI& indptr, const ArrI& indices,
         const ArrD& force, double k_peak, double k_load, double join_pa) {
        auto p = bubble::bindings::map_n(pd, "pd");
        auto f = bubble::bindings::map_n(force, "force");
        bubble::require(support.ndim() == 1 && indptr.ndim() == 1 && indices.ndim() == 1,
                        "support, indptr and indices must be 1-D");
        Eigen::Map<const Eigen::Matrix<bool, Eigen::Dynamic, 1>> s(support.data(),
                                                                   support.shape(0));
        Eigen::Map<const Eigen::VectorXi> ptr(indptr.data(), indptr.shape(0));
        Eigen::Map<const Eigen::VectorXi> idx(indices.data(), indices.shape(0));
        bubble::LoadRegions r;
        {
          py::gil_scoped_release release;
          r = bubble::load_regions(p, s, ptr, idx, f, k_peak, k_load, join_pa);
        }
        return py::make_tuple(py::cast(std::move(r.peak)), py::cast(std::move(r.label)));
      },
      py::arg("pd").noconvert(), py::arg("support").noconvert(), py::arg("indptr").noconvert(),
      py::arg("indices").noconvert(), py::arg("force").noconvert(), py::arg("k_peak"),
      py::arg("k_load"), py::arg("join_pa") = std::numeric_limits<double>::infinity());

  m.def(
      "_fill_load_hulls",
      [](const ArrB& contact, const ArrI& label, const ArrB& support, const ArrD& vertices,
         const ArrD& normals) {
        bubble::require(contact.ndim() == 1 && label.ndim() == 1 && support.ndim() == 1,
                        "contact, label and support must be 1-D");
        using BoolMap = Eigen::Map<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>;
        const BoolMap c(contact.data(), contact.shape(0));
        const BoolMap s(support.data(), support.shape(0));
        const Eigen::Map<const Eigen::VectorXi> l(label.data(), label.shape(0));
        const auto v = bubble::bindings::map_n3(vertices, "vertices");
        const auto nrm = bubble::bindings::map_n3(normals, "normals");
        bubble::LoadHulls r;
        {
          py::gil_scoped_release release;
          r = bubble::fill_load_hulls(c, l, s, v, nrm);
        }
        return py::make_tuple(py::cast(std::move(r.contact)), py::cast(std::move(r.label)));
      },
      py::arg("contact").noconvert(), py::arg("label").noconvert(), py::arg("support").noconvert(),
      py::arg("vertices").noconvert(), py::arg("normals").noconvert());
}
