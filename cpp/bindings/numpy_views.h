// Numpy array types and Eigen views over them, shared by the binding files.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <Eigen/Core>
#include <string>

#include "errors.h"
#include "membrane.h"

namespace bubble::bindings {

namespace py = pybind11;

// With noconvert() on the argument pybind11 never copies these: the Python facades pass
// C-contiguous float64 / int32 / bool arrays, anything else is a TypeError.
using ArrD = py::array_t<double, py::array::c_style>;
using ArrI = py::array_t<int, py::array::c_style>;
using ArrB = py::array_t<bool, py::array::c_style>;
// Accepts any numeric array; pybind11 copies only when it is not C-contiguous float64.
using ArrDCast = py::array_t<double, py::array::c_style | py::array::forcecast>;

// Views without copies; valid while the array lives (hold it across any GIL release).
inline Eigen::Map<const RowMatrixX3d> map_n3(const ArrD& a, const char* name) {
  require(a.ndim() == 2 && a.shape(1) == 3, std::string(name) + " must be N x 3");
  return {a.data(), a.shape(0), 3};
}
inline Eigen::Map<const Eigen::VectorXd> map_n(const ArrD& a, const char* name) {
  require(a.ndim() == 1, std::string(name) + " must be 1-D");
  return {a.data(), a.shape(0)};
}

}  // namespace bubble::bindings
