// Hole filling of depth maps by a push-pull image pyramid.
#pragma once

#include <opencv2/core.hpp>

namespace bubble {

// Fills pixels of `depth` (CV_32F, metres, <= 0 or non-finite = invalid) from their valid
// surroundings. Push: each coarser level averages the valid pixels of 2 x 2 blocks. Pull: from
// the coarsest level down, each hole takes the bilinear upsampling of the level above. Then
// `smooth_iterations` Gauss-Seidel sweeps of the Laplace equation inside the holes smooth the
// seams (towards the harmonic fill). `level` (CV_8U) records, per pixel, 0 for measured depth
// and k when the pixel's 2^k block is the smallest holding measured depth (a hole roughly 2^k
// pixels across); 255 where nothing could be filled (no valid pixel at all). The sweeps skip
// pixels whose level exceeds `smooth_max_level` (holes too large to be trusted anyway, such as
// the background).
void fill_depth(const cv::Mat& depth, cv::Mat& filled, cv::Mat& level, int smooth_iterations = 4,
                int smooth_max_level = 254);

}  // namespace bubble
