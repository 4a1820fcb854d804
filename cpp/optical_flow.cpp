#include "optical_flow.h"

#include <cmath>
#include <opencv2/imgproc.hpp>

#include "errors.h"

namespace bubble {

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

void OpticalFlow::set_reference(const cv::Mat& rgb, cv::Rect roi) {
  require(rgb.type() == CV_8UC3, "reference image must be 8-bit RGB (H x W x 3 uint8)");
  size_ = rgb.size();
  roi_ = roi & cv::Rect(0, 0, rgb.cols, rgb.rows);
  require(roi_.width >= 8 && roi_.height >= 8,
          "flow region of interest is empty or smaller than 8 x 8 pixels");
  reference_ = prepare(rgb);
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
  cv::Mat fwd;
  run(reference_, cur, fwd);
  forward_ = FlowField{fwd, roi_.x, roi_.y, params_.scale};
  if (params_.forward_backward) {
    cv::Mat bwd;
    run(cur, reference_, bwd);
    backward_ = FlowField{bwd, roi_.x, roi_.y, params_.scale};
  } else {
    backward_ = FlowField();
  }
}

}  // namespace bubble
