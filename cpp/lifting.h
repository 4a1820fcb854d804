// Node lifting: flow sampled at node projections, displaced pixel back-projected through depth.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <opencv2/core.hpp>

#include "depth_fill.h"
#include "optical_flow.h"

namespace bubble {

using RowMatrixX3d = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;

// Per-node reasons a lifted node is not trusted (bit flags; 0 = valid).
enum LiftFlag : std::uint8_t {
  kOutsideImage = 1,    // reference or displaced projection outside the image / flow ROI
  kInvalidDepth = 2,    // depth missing, or filled from a hole larger than allowed
  kFlowUnreliable = 4,  // forward-backward inconsistency above the threshold
  kNonFinite = 8,       // non-finite input or result
};

struct PinholeIntrinsics {
  double fx, fy, cx, cy;
};

struct LiftParams {
  // Largest pyramid level (see fill_depth) a depth sample may come from: holes up to about
  // 2^max_fill_level pixels across are bridged, larger ones flag the node.
  int max_fill_level = 4;
  // Forward-backward error above which the flow at a node is unreliable (pixels).
  double fb_threshold = 1.0;
};

// Flow at each pixel (N x 2) from `forward`, and the forward-backward error (N; 0 without a
// backward field). flags gets kOutsideImage / kFlowUnreliable / kNonFinite bits.
void sample_flow(const FlowField& forward, const FlowField* backward,
                 const Eigen::Ref<const RowMatrixX2d>& uv, double fb_threshold,
                 Eigen::Ref<RowMatrixX2d> flow, Eigen::Ref<Eigen::VectorXd> fb_error,
                 Eigen::Ref<Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1>> flags);

// Back-projects pixels (N x 2) through the filled depth map (bilinear) into camera-frame points
// (N x 3, metres). `level` is fill_depth's provenance map. Adds kOutsideImage / kInvalidDepth /
// kNonFinite bits to flags; flagged nodes get the point (0, 0, 0).
void lift_pixels(const cv::Mat& filled, const cv::Mat& level,
                 const Eigen::Ref<const RowMatrixX2d>& uv, const PinholeIntrinsics& K,
                 int max_fill_level, Eigen::Ref<RowMatrixX3d> points,
                 Eigen::Ref<Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1>> flags);

// One frame of tracking: the depth fill runs on its own thread while the flow is computed (the
// two read different images), then the flow is sampled at `uv_ref`, refined, and the displaced
// pixels are lifted. Results are those of compute + sample_flow + refine + fill_depth +
// lift_pixels called one after the other, bit for bit. Wall times (ms): flow (compute, sample,
// refine), fill (on its thread, beside the flow), lift (from the end of the flow: waiting for
// the fill, then lifting).
struct TrackedPixels {
  RowMatrixX2d flow;
  Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1> flow_flags;
  RowMatrixX3d points;  // camera frame, metres (pinhole lift)
  Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1> lift_flags;
  cv::Mat filled, level;  // the fill's results: the tracker's buffers, until its next frame
  double flow_ms = 0, fill_ms = 0, lift_ms = 0;
};

// The tracking stage's state from frame to frame: the flow against its reference and the depth
// fill's buffers.
class PixelTracker {
 public:
  explicit PixelTracker(const FlowParams& params) : flow_(params) {}
  OpticalFlow& flow() { return flow_; }
  const OpticalFlow& flow() const { return flow_; }
  void track(const cv::Mat& rgb, const cv::Mat& depth, const Eigen::Ref<const RowMatrixX2d>& uv_ref,
             double fb_threshold, int smooth_iterations, int max_fill_level,
             const PinholeIntrinsics& K, TrackedPixels& out);

 private:
  OpticalFlow flow_;
  DepthFill fill_;
};

}  // namespace bubble
