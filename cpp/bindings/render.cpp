// Binding of the simulator's rasteriser (private: use bubble_rt.sim.render).
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "errors.h"
#include "numpy_views.h"
#include "rasterizer.h"

namespace py = pybind11;

namespace {

using bubble::bindings::ArrDCast;
using IArr = py::array_t<int32_t, py::array::c_style | py::array::forcecast>;
using UArr = py::array_t<uint8_t, py::array::c_style | py::array::forcecast>;

py::tuple render(const ArrDCast& vertices, const IArr& triangles, const ArrDCast& texcoords,
                 const UArr& texture, double fx, double fy, double cx, double cy, int width,
                 int height, bool rgb, bool shading, double ambient) {
  if (vertices.ndim() != 2 || vertices.shape(1) != 3)
    throw bubble::InputError("render: vertices must be M x 3");
  if (triangles.ndim() != 2 || triangles.shape(1) != 3)
    throw bubble::InputError("render: triangles must be T x 3");
  if (texcoords.ndim() != 2 || texcoords.shape(1) != 2)
    throw bubble::InputError("render: texcoords must be M x 2");
  if (texture.ndim() != 2 && texture.ndim() != 3)
    throw bubble::InputError("render: texture must be H x W or H x W x C");
  Eigen::Map<const bubble::RowMatrixX3d> V(vertices.data(), vertices.shape(0), 3);
  Eigen::Map<const bubble::RowMatrixX3i> T(triangles.data(), triangles.shape(0), 3);
  Eigen::Map<const bubble::RowMatrixX2d> UV(texcoords.data(), texcoords.shape(0), 2);
  bubble::TextureView tex;
  tex.data = texture.data();
  tex.height = static_cast<int>(texture.shape(0));
  tex.width = static_cast<int>(texture.ndim() > 1 ? texture.shape(1) : 0);
  tex.channels = texture.ndim() == 3 ? static_cast<int>(texture.shape(2)) : 1;
  bubble::RasterCamera cam{fx, fy, cx, cy, width, height};
  bubble::RenderOptions opt;
  opt.rgb = rgb;
  opt.shading = shading;
  opt.ambient = ambient;
  bubble::RenderOutput out;
  {
    py::gil_scoped_release release;
    out = bubble::rasterize(V, T, UV, tex, cam, opt);
  }
  py::array_t<float> depth({height, width});
  std::copy(out.depth.begin(), out.depth.end(), depth.mutable_data());
  py::array_t<int32_t> face({height, width});
  std::copy(out.face.begin(), out.face.end(), face.mutable_data());
  py::object image = py::none();
  if (rgb) {
    py::array_t<uint8_t> img({height, width, 3});
    std::copy(out.rgb.begin(), out.rgb.end(), img.mutable_data());
    image = img;
  }
  return py::make_tuple(depth, image, face);
}

}  // namespace

void bind_render(py::module_& m) {
  m.def("render_mesh", &render, py::arg("vertices"), py::arg("triangles"), py::arg("texcoords"),
        py::arg("texture"), py::arg("fx"), py::arg("fy"), py::arg("cx"), py::arg("cy"),
        py::arg("width"), py::arg("height"), py::arg("rgb") = true, py::arg("shading") = true,
        py::arg("ambient") = 0.55,
        "Rasterise a mesh (camera-frame vertices) to (depth float32 H x W, rgb uint8 H x W x 3 or "
        "None, face int32 H x W). Raises ValueError on bad input.");
}
