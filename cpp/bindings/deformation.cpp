// Private bindings for the RGBD deformation stage (public API: bubble_rt.estimation.deformation;
// depth filling also bubble_rt.estimation.fitting).
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstdint>
#include <cstring>
#include <tuple>

#include "depth_fill.h"
#include "errors.h"
#include "lifting.h"
#include "neighbour_median.h"
#include "numpy_views.h"
#include "optical_flow.h"

namespace py = pybind11;
using bubble::RowMatrixX2d;
using bubble::RowMatrixX3d;

namespace {

using U8Image = py::array_t<std::uint8_t, py::array::c_style>;
using F32Image = py::array_t<float, py::array::c_style | py::array::forcecast>;
using bubble::bindings::ArrD;
using bubble::bindings::ArrDCast;
using FlagVector = Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1>;

// A cv::Mat header over a numpy RGB image (no copy).
cv::Mat rgb_view(const U8Image& rgb) {
  bubble::require(rgb.ndim() == 3 && rgb.shape(2) == 3, "rgb must be H x W x 3 uint8");
  return cv::Mat(static_cast<int>(rgb.shape(0)), static_cast<int>(rgb.shape(1)), CV_8UC3,
                 const_cast<std::uint8_t*>(rgb.data()));
}

cv::Mat f32_view(const F32Image& img, const char* what) {
  bubble::require(img.ndim() == 2, std::string(what) + " must be a 2-D H x W array");
  return cv::Mat(static_cast<int>(img.shape(0)), static_cast<int>(img.shape(1)), CV_32F,
                 const_cast<float*>(img.data()));
}

Eigen::Map<const RowMatrixX2d> uv_view(const ArrDCast& uv) {
  bubble::require(uv.ndim() == 2 && uv.shape(1) == 2, "uv must be N x 2");
  return Eigen::Map<const RowMatrixX2d>(uv.data(), uv.shape(0), 2);
}

template <typename T>
py::array_t<T> mat_to_array(const cv::Mat& m, int channels) {
  std::vector<py::ssize_t> shape = {m.rows, m.cols};
  if (channels > 1) shape.push_back(channels);
  py::array_t<T> out(shape);
  const size_t row_bytes = static_cast<size_t>(m.cols) * channels * sizeof(T);
  for (int y = 0; y < m.rows; ++y)
    std::memcpy(reinterpret_cast<char*>(out.mutable_data()) + y * row_bytes, m.ptr(y), row_bytes);
  return out;
}

}  // namespace

void bind_deformation(py::module_& m) {
  py::class_<bubble::PixelTracker>(m, "_PixelTracker")
      .def(py::init([](int method, int dis_preset, double pyr_scale, int levels, int winsize,
                       int iterations, int poly_n, double poly_sigma, bool gaussian, double scale,
                       bool forward_backward, int dis_finest_scale, int dis_refinement_iterations,
                       int dis_patch_stride, int refine_window) {
             bubble::FlowParams p;
             bubble::require(method == 0 || method == 1, "method must be 0 (Farneback) or 1 (DIS)");
             p.method = static_cast<bubble::FlowMethod>(method);
             p.dis_preset = dis_preset;
             p.farneback = {pyr_scale, levels, winsize, iterations, poly_n, poly_sigma, gaussian};
             p.scale = scale;
             p.forward_backward = forward_backward;
             p.dis_finest_scale = dis_finest_scale;
             p.dis_refinement_iterations = dis_refinement_iterations;
             p.dis_patch_stride = dis_patch_stride;
             p.refine_window = refine_window;
             return new bubble::PixelTracker(p);
           }),
           py::arg("method"), py::arg("dis_preset"), py::arg("pyr_scale"), py::arg("levels"),
           py::arg("winsize"), py::arg("iterations"), py::arg("poly_n"), py::arg("poly_sigma"),
           py::arg("gaussian"), py::arg("scale"), py::arg("forward_backward"),
           py::arg("dis_finest_scale") = -1, py::arg("dis_refinement_iterations") = -1,
           py::arg("dis_patch_stride") = -1, py::arg("refine_window") = 0)
      .def(
          "set_reference",
          [](bubble::PixelTracker& self, const U8Image& rgb, int x, int y, int w, int h) {
            cv::Mat img = rgb_view(rgb);
            py::gil_scoped_release release;
            self.flow().set_reference(img, cv::Rect(x, y, w, h));
          },
          py::arg("rgb"), py::arg("x"), py::arg("y"), py::arg("w"), py::arg("h"))
      .def(
          "compute",
          [](bubble::PixelTracker& self, const U8Image& rgb) {
            cv::Mat img = rgb_view(rgb);
            py::gil_scoped_release release;
            self.flow().compute(img);
          },
          py::arg("rgb"))
      .def(
          "sample",
          [](const bubble::PixelTracker& tracker, const ArrDCast& uv, double fb_threshold) {
            const bubble::OpticalFlow& self = tracker.flow();
            auto pts = uv_view(uv);
            RowMatrixX2d flow(pts.rows(), 2);
            Eigen::VectorXd fb(pts.rows());
            FlagVector flags = FlagVector::Zero(pts.rows());
            {
              py::gil_scoped_release release;
              const bubble::FlowField* bwd = self.backward().empty() ? nullptr : &self.backward();
              bubble::sample_flow(self.forward(), bwd, pts, fb_threshold, flow, fb, flags);
              self.refine(pts, flags, flow);
            }
            return std::make_tuple(flow, fb, flags);
          },
          py::arg("uv"), py::arg("fb_threshold"))
      .def("dense",
           [](const bubble::PixelTracker& self) {
             const bubble::FlowField& f = self.flow().forward();
             bubble::require(!f.empty(), "no flow has been computed");
             return std::make_tuple(mat_to_array<float>(f.flow, 2), f.x0, f.y0, f.scale);
           })
      .def(
          "track",
          [](bubble::PixelTracker& self, const U8Image& rgb, const F32Image& depth,
             const ArrDCast& uv_ref, double fb_threshold, int smooth_iterations, int max_fill_level,
             double fx, double fy, double cx, double cy, bool want_filled) {
            cv::Mat img = rgb_view(rgb);
            cv::Mat d = f32_view(depth, "depth");
            auto pts = uv_view(uv_ref);
            bubble::TrackedPixels out;
            {
              py::gil_scoped_release release;
              self.track(img, d, pts, fb_threshold, smooth_iterations, max_fill_level,
                         bubble::PinholeIntrinsics{fx, fy, cx, cy}, out);
            }
            py::object filled = py::none();
            if (want_filled) filled = mat_to_array<float>(out.filled, 1);
            py::dict ms;
            ms["flow"] = out.flow_ms;
            ms["fill"] = out.fill_ms;
            ms["lift"] = out.lift_ms;
            return py::make_tuple(std::move(out.flow), std::move(out.flow_flags),
                                  std::move(out.points), std::move(out.lift_flags), filled, ms);
          },
          py::arg("rgb"), py::arg("depth"), py::arg("uv_ref"), py::arg("fb_threshold"),
          py::arg("smooth_iterations"), py::arg("max_fill_level"), py::arg("fx"), py::arg("fy"),
          py::arg("cx"), py::arg("cy"), py::arg("want_filled"))
      .def_property_readonly("roi", [](const bubble::PixelTracker& self) {
        const cv::Rect r = self.flow().roi();
        return std::make_tuple(r.x, r.y, r.width, r.height);
      });

  // OpenCV's parallel loops (the DIS flow's patch search). Debian's OpenCV runs them on TBB,
  // which ignores OPENCV_FOR_THREADS_NUM: only cv::setNumThreads sets their thread count.
  m.def(
      "_set_opencv_threads", [](int n) { cv::setNumThreads(n); }, py::arg("n"),
      "Threads of OpenCV's parallel loops in the C++ core (cv::setNumThreads).");
  m.def("_opencv_threads", [] { return cv::getNumThreads(); });

  m.def(
      "_fill_depth",
      [](const F32Image& depth, int smooth_iterations, int smooth_max_level) {
        cv::Mat d = f32_view(depth, "depth");
        cv::Mat filled, level;
        {
          py::gil_scoped_release release;
          bubble::fill_depth(d, filled, level, smooth_iterations, smooth_max_level);
        }
        return std::make_tuple(mat_to_array<float>(filled, 1),
                               mat_to_array<std::uint8_t>(level, 1));
      },
      py::arg("depth"), py::arg("smooth_iterations") = 4, py::arg("smooth_max_level") = 254);

  m.def(
      "_neighbour_outliers",
      [](const ArrD& U, const py::array_t<bool, py::array::c_style>& measured,
         const py::array_t<std::int64_t, py::array::c_style>& neighbours, double tol,
         double relative_tol) {
        const auto u = bubble::bindings::map_n3(U, "U");
        bubble::require(measured.ndim() == 1, "measured must be 1-D");
        bubble::require(neighbours.ndim() == 2, "neighbours must be N x W");
        const Eigen::Map<const bubble::BoolVector> meas(measured.data(), measured.shape(0));
        const Eigen::Map<const bubble::NeighbourTable> nb(neighbours.data(), neighbours.shape(0),
                                                          neighbours.shape(1));
        py::gil_scoped_release release;
        return bubble::neighbour_outliers(u, meas, nb, tol, relative_tol);
      },
      py::arg("U").noconvert(), py::arg("measured").noconvert(), py::arg("neighbours").noconvert(),
      py::arg("tol"), py::arg("relative_tol") = 0.0);

  m.def(
      "_lift_pixels",
      [](const F32Image& filled, const U8Image& level, const ArrDCast& uv, double fx, double fy,
         double cx, double cy, int max_fill_level) {
        cv::Mat d = f32_view(filled, "filled depth");
        bubble::require(level.ndim() == 2, "level must be a 2-D H x W uint8 array");
        cv::Mat l(static_cast<int>(level.shape(0)), static_cast<int>(level.shape(1)), CV_8U,
                  const_cast<std::uint8_t*>(level.data()));
        auto pts = uv_view(uv);
        RowMatrixX3d points(pts.rows(), 3);
        FlagVector flags = FlagVector::Zero(pts.rows());
        {
          py::gil_scoped_release release;
          bubble::lift_pixels(d, l, pts, bubble::PinholeIntrinsics{fx, fy, cx, cy}, max_fill_level,
                              points, flags);
        }
        return std::make_tuple(points, flags);
      },
      py::arg("filled"), py::arg("level"), py::arg("uv"), py::arg("fx"), py::arg("fy"),
      py::arg("cx"), py::arg("cy"), py::arg("max_fill_level"));
}
