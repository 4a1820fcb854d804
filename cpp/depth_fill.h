// Hole filling of depth maps by a push-pull image pyramid.
#pragma once

#include <opencv2/core.hpp>
#include <vector>

namespace bubble {

// Fills pixels of a depth map (CV_32F, metres, <= 0 or non-finite = invalid) from their valid
// surroundings. Push: each coarser level averages the valid pixels of 2 x 2 blocks. Pull: from
// the coarsest level down, each hole takes the bilinear upsampling of the level above. Then
// `smooth_iterations` Gauss-Seidel sweeps of the Laplace equation inside the holes smooth the
// seams (towards the harmonic fill). level() (CV_8U) records, per pixel, 0 for measured depth
// and k when the pixel's 2^k block is the smallest holding measured depth (a hole roughly 2^k
// pixels across); 255 where nothing could be filled (no valid pixel at all). The sweeps skip
// pixels whose level exceeds `smooth_max_level` (holes too large to be trusted anyway, such as
// the background).
//
// The pyramid's buffers live from one fill to the next: allocated afresh, a few megabytes per
// frame page-faulted back in every time, which measured as a third of the fill's time.
class DepthFill {
 public:
  void fill(const cv::Mat& depth, int smooth_iterations = 4, int smooth_max_level = 254);
  // The last fill's results (CV_32F, CV_8U; their buffers are reused by the next fill).
  const cv::Mat& filled() const { return pyramid_.front().d; }
  const cv::Mat& level() const { return level_; }

 private:
  struct Level {
    cv::Mat d;  // CV_32F depth, valid where w > 0
    cv::Mat w;  // CV_32F weight (number of valid source pixels, normalised to the block)
  };
  // A hole pixel of the sweeps and its four neighbours (itself at the image border).
  struct Cell {
    int idx, left, right, up, down;
  };
  long load_base(const cv::Mat& depth);
  int build_pyramid();
  void mark_levels(int n_levels, int smooth_max_level);

  std::vector<Level> pyramid_ = std::vector<Level>(1);
  std::vector<Cell> smooth_;
  cv::Mat level_;
};

// One fill with buffers of its own.
void fill_depth(const cv::Mat& depth, cv::Mat& filled, cv::Mat& level, int smooth_iterations = 4,
                int smooth_max_level = 254);

}  // namespace bubble
