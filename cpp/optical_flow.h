// Dense optical flow from a reference image to the current one, over a region of interest,
// and its Lucas-Kanade refinement at given pixels.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <opencv2/core.hpp>
#include <opencv2/video/tracking.hpp>
#include <vector>

namespace bubble {

enum class FlowMethod { kFarneback = 0, kDis = 1 };

// cv::calcOpticalFlowFarneback parameters. Defaults are OpenCV's documented example values;
// FarnebackParams::Heavy() is the public implementation's heavier set.
struct FarnebackParams {
  double pyr_scale = 0.5;
  int levels = 3;
  int winsize = 15;
  int iterations = 3;
  int poly_n = 5;
  double poly_sigma = 1.2;
  bool gaussian = false;  // OPTFLOW_FARNEBACK_GAUSSIAN window instead of a box
  static FarnebackParams Heavy() { return {0.5, 30, 50, 5, 7, 1.5, true}; }
};

struct FlowParams {
  FlowMethod method = FlowMethod::kDis;
  // cv::DISOpticalFlow preset: 0 ultrafast, 1 fast, 2 medium.
  int dis_preset = 2;
  // Overrides of the preset (-1 keeps the preset's value): finest pyramid level the flow is
  // computed at (0 = full resolution of the working image) and variational refinement
  // iterations.
  int dis_finest_scale = -1;
  int dis_refinement_iterations = -1;
  // Pixels between the centres of neighbouring patches (-1 keeps the preset's 4): the patch
  // search's cost falls with its square.
  int dis_patch_stride = -1;
  FarnebackParams farneback;
  // Images are resized by this factor (0 < scale <= 1) before the flow; flow is returned in
  // full-resolution pixels.
  double scale = 1.0;
  // Also compute the backward flow (current -> reference) for a consistency check.
  bool forward_backward = false;
  // Window (odd, working-image pixels) of the Lucas-Kanade refinement of the flow sampled at
  // the nodes (OpticalFlow::refine); 0: no refinement.
  int refine_window = 0;
};

using RowMatrixX2d = Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::RowMajor>;

// A flow field over a sub-image, possibly at reduced resolution. Full-resolution pixel
// (u, v) sits at field coordinates ((u - x0 + 0.5) * scale - 0.5, (v - y0 + 0.5) * scale - 0.5).
struct FlowField {
  cv::Mat flow;  // CV_32FC2, field pixels
  int x0 = 0;
  int y0 = 0;
  double scale = 1.0;
  bool empty() const { return flow.empty(); }
  // Bilinear flow at a full-resolution pixel, in full-resolution pixels. False when the pixel
  // lies outside the field.
  bool sample(double u, double v, double* du, double* dv) const;
};

class OpticalFlow {
 public:
  explicit OpticalFlow(const FlowParams& params);
  // rgb: 8-bit 3-channel RGB image; roi clipped to the image.
  void set_reference(const cv::Mat& rgb, cv::Rect roi);
  // Computes the flow reference -> rgb over the ROI (and back when forward_backward).
  void compute(const cv::Mat& rgb);
  // Refines the flow sampled at full-resolution pixels uv (N x 2, full-resolution pixels, in
  // place) by Lucas-Kanade on the working images of the last compute(), started from it: the
  // dense field is smooth over its patches, the refinement matches a window at each pixel
  // itself. Pixels with flags set are left as they are, and so is a pixel whose window is not
  // tracked or would move further than kMaxRefineStepPx from the dense flow. No-op when
  // refine_window is 0.
  void refine(const Eigen::Ref<const RowMatrixX2d>& uv,
              const Eigen::Ref<const Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1>>& flags,
              Eigen::Ref<RowMatrixX2d> flow) const;
  const FlowField& forward() const { return forward_; }
  const FlowField& backward() const { return backward_; }
  const FlowParams& params() const { return params_; }
  cv::Rect roi() const { return roi_; }
  cv::Size image_size() const { return size_; }

 private:
  cv::Mat prepare(const cv::Mat& rgb) const;
  cv::Mat dense_input(const cv::Mat& working) const;
  void run(const cv::Mat& from, const cv::Mat& to, cv::Mat& out);

  FlowParams params_;
  cv::Ptr<cv::DISOpticalFlow> dis_;
  // DIS runs on images already reduced to its finest pyramid level (1 / 2^k of the working
  // image): asked to reduce them itself, it would reduce the reference again every frame and
  // upsample its field to the working image's size, a fresh multi-megabyte array each frame
  // (measured: 0.5-0.9 ms of a 4 ms compute() at 628 x 460). Its field stays at that level,
  // 1 / dense_factor_ of the working image; FlowField samples it there.
  int finest_scale_ = 0;  // the preset's finest level, or the override
  int dense_factor_ = 1;
  cv::Mat reference_;        // grey ROI at working scale
  cv::Mat dense_reference_;  // reference_ at DIS's finest level
  // The refinement's reference (padded, with its derivatives: built once per reference) and
  // the last compute()'s padded current image.
  std::vector<cv::Mat> reference_pyramid_, current_pyramid_;
  cv::Rect roi_;
  cv::Size size_;
  FlowField forward_;
  FlowField backward_;
};

}  // namespace bubble
