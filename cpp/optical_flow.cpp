#include "optical_flow.h"

#include <cmath>
#include <opencv2/imgproc.hpp>

#include "errors.h"

namespace bubble {
namespace {

// The refinement starts at the dense flow, so it runs on the working image alone (no pyramid
// levels above it) and needs few steps.
constexpr int kRefineIterations = 10;
constexpr double kRefineEpsilon = 0.03;  // working pixels
// Weaker gradients than this (OpenCV's normalised minimum eigenvalue) are not refined: a
// window without texture has no position of its own.
constexpr double kRefineMinEigen = 1e-4;
// A refinement that moves further from the dense flow has locked onto another texture.
constexpr double kMaxRefineStepPx = 2.0;  // full-resolution pixels
// The smallest image side cv::DISOpticalFlow accepts.
constexpr int kDisMinSide = 12;

}  // namespace

bool FlowField::sample(double u, double v, double* du, double* dv) const {
  if (flow.empty() || !std::isfinite(u) || !std::isfinite(v)) return false;
  const double x = (u - x0 + 0.5) * scale - 0.5;
  const double y = (v - y0 + 0.5) * scale - 0.5;
  const int w = flow.cols, h = flow.rows;
  // Half a field pixel of slack at the border, clamped, so nodes on the ROI edge still sample.
  if (x < -0.5 || y < -0.5 || x > w - 0.5 || y > h - 0.5) return false;
  const double xc = std::min(std::max(x, 0.0), static_cast<double>(w - 1));
  const double yc = std::min(std::max(y, 0.0), static_cast<double>(h - 1));
  const int xi = std::min(static_cast<int>(xc), std::max(w - 2, 0));
  const int yi = std::min(static_cast<int>(yc), std::max(h - 2, 0));
  const double ax = w > 1 ? xc - xi : 0.0, ay = h > 1 ? yc - yi : 0.0;
  const int xj = std::min(xi + 1, w - 1), yj = std::min(yi + 1, h - 1);
  const cv::Vec2f& f00 = flow.at<cv::Vec2f>(yi, xi);
  const cv::Vec2f& f01 = flow.at<cv::Vec2f>(yi, xj);
  const cv::Vec2f& f10 = flow.at<cv::Vec2f>(yj, xi);
  const cv::Vec2f& f11 = flow.at<cv::Vec2f>(yj, xj);
  for (int c = 0; c < 2; ++c) {
    const double top = (1 - ax) * f00[c] + ax * f01[c];
    const double bot = (1 - ax) * f10[c] + ax * f11[c];
    const double val = ((1 - ay) * top + ay * bot) / scale;
    (c == 0 ? *du : *dv) = val;
  }
  return std::isfinite(*du) && std::isfinite(*dv);
}

OpticalFlow::OpticalFlow(const FlowParams& params) : params_(params) {
  require(params.scale > 0.0 && params.scale <= 1.0, "flow scale must be in (0, 1]");
  require(params.refine_window == 0 || (params.refine_window >= 5 && params.refine_window % 2 == 1),
          "refinement window must be 0 (none) or odd and >= 5 pixels");
  if (params.method == FlowMethod::kDis) {
    require(params.dis_preset >= 0 && params.dis_preset <= 2,
            "DIS preset must be 0 (ultrafast), 1 (fast) or 2 (medium)");
    dis_ = cv::DISOpticalFlow::create(params.dis_preset);
    if (params.dis_finest_scale >= 0) dis_->setFinestScale(params.dis_finest_scale);
    if (params.dis_refinement_iterations >= 0)
      dis_->setVariationalRefinementIterations(params.dis_refinement_iterations);
    if (params.dis_patch_stride >= 0) {
      require(params.dis_patch_stride >= 1 && params.dis_patch_stride <= dis_->getPatchSize(),
              "DIS patch stride must be between 1 and the patch size");
      dis_->setPatchStride(params.dis_patch_stride);
    }
    finest_scale_ = dis_->getFinestScale();
    require(finest_scale_ >= 0 && finest_scale_ <= 8, "DIS finest scale must be 0..8");
  } else {
    const FarnebackParams& f = params.farneback;
    require(f.pyr_scale > 0.0 && f.pyr_scale < 1.0, "Farneback pyr_scale must be in (0, 1)");
    require(f.levels >= 1 && f.winsize >= 3 && f.iterations >= 1,
            "Farneback levels, winsize and iterations must be positive (winsize >= 3)");
    require(f.poly_n == 5 || f.poly_n == 7, "Farneback poly_n must be 5 or 7");
    require(f.poly_sigma > 0.0, "Farneback poly_sigma must be positive");
  }
}

cv::Mat OpticalFlow::prepare(const cv::Mat& rgb) const {
  require(rgb.type() == CV_8UC3, "flow image must be 8-bit RGB (H x W x 3 uint8)");
  cv::Mat grey;
  cv::cvtColor(rgb(roi_), grey, cv::COLOR_RGB2GRAY);
  if (params_.scale < 1.0) {
    cv::Mat small;
    const cv::Size sz(std::max(1, static_cast<int>(std::lround(grey.cols * params_.scale))),
                      std::max(1, static_cast<int>(std::lround(grey.rows * params_.scale))));
    cv::resize(grey, small, sz, 0, 0, cv::INTER_AREA);
    return small;
  }
  return grey;
}

// The working image reduced to DIS's finest level as DIS itself reduces it (sizes rounded
// down, area averaging), so that its pyramid and field are the same as on the working image.
cv::Mat OpticalFlow::dense_input(const cv::Mat& working) const {
  if (dense_factor_ == 1) return working;
  const int f = dense_factor_;
  cv::Mat small;
  cv::resize(working, small, cv::Size(working.cols / f, working.rows / f), 0, 0, cv::INTER_AREA);
  return small;
}

void OpticalFlow::set_reference(const cv::Mat& rgb, cv::Rect roi) {
  require(rgb.type() == CV_8UC3, "reference image must be 8-bit RGB (H x W x 3 uint8)");
  size_ = rgb.size();
  roi_ = roi & cv::Rect(0, 0, rgb.cols, rgb.rows);
  require(roi_.width >= 8 && roi_.height >= 8,
          "flow region of interest is empty or smaller than 8 x 8 pixels");
  reference_ = prepare(rgb);
  if (dis_) {
    // DIS refuses images under 12 pixels; an image that small it reduces itself (the same
    // pyramid, from the same one-step reduction).
    const int f = 1 << finest_scale_;
    const bool reduce = reference_.cols / f >= kDisMinSide && reference_.rows / f >= kDisMinSide;
    dense_factor_ = reduce ? f : 1;
    dis_->setFinestScale(reduce ? 0 : finest_scale_);
  }
  dense_reference_ = dense_input(reference_);
  reference_pyramid_.clear();
  current_pyramid_.clear();
  if (params_.refine_window > 0) {
    const cv::Size window(params_.refine_window, params_.refine_window);
    cv::buildOpticalFlowPyramid(reference_, reference_pyramid_, window, 0, true);
  }
  forward_ = FlowField();
  backward_ = FlowField();
}

void OpticalFlow::run(const cv::Mat& from, const cv::Mat& to, cv::Mat& out) {
  // DISOpticalFlow uses a pre-sized output as its initial guess: always start from nothing.
  out.release();
  if (params_.method == FlowMethod::kDis) {
    dis_->calc(from, to, out);
  } else {
    const FarnebackParams& f = params_.farneback;
    cv::calcOpticalFlowFarneback(from, to, out, f.pyr_scale, f.levels, f.winsize, f.iterations,
                                 f.poly_n, f.poly_sigma,
                                 f.gaussian ? cv::OPTFLOW_FARNEBACK_GAUSSIAN : 0);
  }
}

void OpticalFlow::compute(const cv::Mat& rgb) {
  require(!reference_.empty(), "optical flow has no reference image");
  require(rgb.size() == size_, "current image size differs from the reference image size");
  const cv::Mat cur = prepare(rgb);
  const cv::Mat dense_cur = dense_input(cur);
  const double field_scale = params_.scale / dense_factor_;
  cv::Mat fwd;
  run(dense_reference_, dense_cur, fwd);
  forward_ = FlowField{fwd, roi_.x, roi_.y, field_scale};
  if (params_.refine_window > 0) {
    const cv::Size window(params_.refine_window, params_.refine_window);
    cv::buildOpticalFlowPyramid(cur, current_pyramid_, window, 0, false);
  }
  if (params_.forward_backward) {
    cv::Mat bwd;
    run(dense_cur, dense_reference_, bwd);
    backward_ = FlowField{bwd, roi_.x, roi_.y, field_scale};
  } else {
    backward_ = FlowField();
  }
}

void OpticalFlow::refine(
    const Eigen::Ref<const RowMatrixX2d>& uv,
    const Eigen::Ref<const Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1>>& flags,
    Eigen::Ref<RowMatrixX2d> flow) const {
  if (params_.refine_window == 0) return;
  require(!current_pyramid_.empty(), "refine: no flow has been computed");
  require(uv.rows() == flow.rows() && uv.rows() == flags.rows(),
          "refine: uv, flags and flow differ in length");
  // Working-image coordinates (FlowField's convention) of the unflagged pixels.
  const double s = params_.scale;
  std::vector<cv::Point2f> start, moved;
  std::vector<Eigen::Index> index;
  for (Eigen::Index i = 0; i < uv.rows(); ++i) {
    if (flags(i) != 0) continue;
    const float x = static_cast<float>((uv(i, 0) - roi_.x + 0.5) * s - 0.5);
    const float y = static_cast<float>((uv(i, 1) - roi_.y + 0.5) * s - 0.5);
    start.emplace_back(x, y);
    moved.emplace_back(x + static_cast<float>(flow(i, 0) * s),
                       y + static_cast<float>(flow(i, 1) * s));
    index.push_back(i);
  }
  if (start.empty()) return;
  // Lucas-Kanade from the dense flow, on the working images alone.
  std::vector<unsigned char> tracked;
  std::vector<float> error;
  const cv::Size window(params_.refine_window, params_.refine_window);
  const cv::TermCriteria stop(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, kRefineIterations,
                              kRefineEpsilon);
  cv::calcOpticalFlowPyrLK(reference_pyramid_, current_pyramid_, start, moved, tracked, error,
                           window, 0, stop, cv::OPTFLOW_USE_INITIAL_FLOW, kRefineMinEigen);
  // Keep what was tracked and stayed near the dense flow.
  for (size_t j = 0; j < start.size(); ++j) {
    const Eigen::Index i = index[j];
    const double du = (moved[j].x - start[j].x) / s, dv = (moved[j].y - start[j].y) / s;
    const bool near = std::hypot(du - flow(i, 0), dv - flow(i, 1)) < kMaxRefineStepPx;
    if (tracked[j] && std::isfinite(du) && std::isfinite(dv) && near) {
      flow(i, 0) = du;
      flow(i, 1) = dv;
    }
  }
}

}  // namespace bubble
