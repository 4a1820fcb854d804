#include "lifting.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <exception>
#include <thread>

#include "depth_fill.h"
#include "errors.h"

namespace bubble {

void sample_flow(const FlowField& forward, const FlowField* backward,
                 const Eigen::Ref<const RowMatrixX2d>& uv, double fb_threshold,
                 Eigen::Ref<RowMatrixX2d> flow, Eigen::Ref<Eigen::VectorXd> fb_error,
                 Eigen::Ref<Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1>> flags) {
  const Eigen::Index n = uv.rows();
  require(flow.rows() == n && fb_error.rows() == n && flags.rows() == n,
          "sample_flow: output sizes differ from the number of pixels");
  require(!forward.empty(), "sample_flow: no flow has been computed");
  const bool fb = backward != nullptr && !backward->empty();
  for (Eigen::Index i = 0; i < n; ++i) {
    double du = 0, dv = 0;
    fb_error(i) = 0.0;
    if (!std::isfinite(uv(i, 0)) || !std::isfinite(uv(i, 1))) {
      flags(i) |= kNonFinite;
      flow.row(i).setZero();
      continue;
    }
    if (!forward.sample(uv(i, 0), uv(i, 1), &du, &dv)) {
      flags(i) |= kOutsideImage;
      flow.row(i).setZero();
      continue;
    }
    flow(i, 0) = du;
    flow(i, 1) = dv;
    if (fb) {
      double bu = 0, bv = 0;
      if (!backward->sample(uv(i, 0) + du, uv(i, 1) + dv, &bu, &bv)) {
        flags(i) |= kOutsideImage;
        continue;
      }
      fb_error(i) = std::hypot(du + bu, dv + bv);
      if (fb_error(i) > fb_threshold) flags(i) |= kFlowUnreliable;
    }
  }
}

void lift_pixels(const cv::Mat& filled, const cv::Mat& level,
                 const Eigen::Ref<const RowMatrixX2d>& uv, const PinholeIntrinsics& K,
                 int max_fill_level, Eigen::Ref<RowMatrixX3d> points,
                 Eigen::Ref<Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1>> flags) {
  require(filled.type() == CV_32F && level.type() == CV_8U && filled.size() == level.size(),
          "lift_pixels: depth must be float32 and its level map uint8 of the same size");
  const Eigen::Index n = uv.rows();
  require(points.rows() == n && flags.rows() == n,
          "lift_pixels: output sizes differ from the number of pixels");
  const int w = filled.cols, h = filled.rows;
  for (Eigen::Index i = 0; i < n; ++i) {
    points.row(i).setZero();
    const double u = uv(i, 0), v = uv(i, 1);
    if (!std::isfinite(u) || !std::isfinite(v)) {
      flags(i) |= kNonFinite;
      continue;
    }
    // Pixel centres are at integer coordinates; allow half a pixel beyond the outer centres.
    if (u < -0.5 || v < -0.5 || u > w - 0.5 || v > h - 0.5) {
      flags(i) |= kOutsideImage;
      continue;
    }
    const double uc = std::min(std::max(u, 0.0), w - 1.0);
    const double vc = std::min(std::max(v, 0.0), h - 1.0);
    const int x0 = std::min(static_cast<int>(uc), std::max(w - 2, 0));
    const int y0 = std::min(static_cast<int>(vc), std::max(h - 2, 0));
    const int x1 = std::min(x0 + 1, w - 1), y1 = std::min(y0 + 1, h - 1);
    const double ax = uc - x0, ay = vc - y0;
    const int worst =
        std::max(std::max(level.at<std::uint8_t>(y0, x0), level.at<std::uint8_t>(y0, x1)),
                 std::max(level.at<std::uint8_t>(y1, x0), level.at<std::uint8_t>(y1, x1)));
    if (worst > max_fill_level) {
      flags(i) |= kInvalidDepth;
      continue;
    }
    const double z =
        (1 - ay) * ((1 - ax) * filled.at<float>(y0, x0) + ax * filled.at<float>(y0, x1)) +
        ay * ((1 - ax) * filled.at<float>(y1, x0) + ax * filled.at<float>(y1, x1));
    if (!std::isfinite(z) || z <= 0) {
      flags(i) |= kInvalidDepth;
      continue;
    }
    points(i, 0) = (u - K.cx) / K.fx * z;
    points(i, 1) = (v - K.cy) / K.fy * z;
    points(i, 2) = z;
  }
}

namespace {
double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}
}  // namespace

void PixelTracker::track(const cv::Mat& rgb, const cv::Mat& depth,
                         const Eigen::Ref<const RowMatrixX2d>& uv_ref, double fb_threshold,
                         int smooth_iterations, int max_fill_level, const PinholeIntrinsics& K,
                         TrackedPixels& out) {
  require(depth.type() == CV_32F, "track: depth must be float32");
  const Eigen::Index n = uv_ref.rows();
  const auto t0 = std::chrono::steady_clock::now();
  // The fill reads only the depth image, the flow only the colour one: run them side by side.
  std::exception_ptr fill_error;
  std::thread filler([&] {
    try {
      fill_.fill(depth, smooth_iterations, max_fill_level + 1);
    } catch (...) {
      fill_error = std::current_exception();
    }
    out.fill_ms = ms_since(t0);
  });
  out.flow.resize(n, 2);
  out.flow_flags = Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1>::Zero(n);
  std::exception_ptr flow_error;
  try {
    flow_.compute(rgb);
    Eigen::VectorXd fb(n);
    const FlowField* bwd = flow_.backward().empty() ? nullptr : &flow_.backward();
    sample_flow(flow_.forward(), bwd, uv_ref, fb_threshold, out.flow, fb, out.flow_flags);
    flow_.refine(uv_ref, out.flow_flags, out.flow);
  } catch (...) {
    flow_error = std::current_exception();
  }
  const auto t_flow = std::chrono::steady_clock::now();
  out.flow_ms = ms_since(t0);
  filler.join();  // always joined, also when the flow failed
  if (flow_error) std::rethrow_exception(flow_error);
  if (fill_error) std::rethrow_exception(fill_error);
  out.filled = fill_.filled();
  out.level = fill_.level();
  const RowMatrixX2d uv = uv_ref + out.flow;
  out.points.resize(n, 3);
  out.lift_flags = Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1>::Zero(n);
  lift_pixels(out.filled, out.level, uv, K, max_fill_level, out.points, out.lift_flags);
  out.lift_ms = ms_since(t_flow);
}

}  // namespace bubble
