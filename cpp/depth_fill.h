// Hole filling of depth maps by a push-pull image pyramid.
#pragma once

#include <opencv2/core.hpp>

namespace bubble {

// Fills pixels of `depth` (CV_32F, metres, <= 0 or non-finite = invalid) from their valid
// surroundings. Push: each coarser level averages the valid pixels of 2 x 2 blocks. Pull: from
// the coarsest level down, each hole takes the bilinear upsampling of the level above. Then
// `smooth_iterations` Jacobi sweeps of the Laplace equation inside the holes make the fill
// harmonic (exact for planar depth). `level` (CV_8U) records, per pixel, 0 for measured depth
// and k for a value pulled from pyramid level k (a hole roughly 2^k pixels across); 255 where
// nothing could be filled (no valid pixel at all).
void fill_depth(const cv::Mat& depth, cv::Mat& filled, cv::Mat& level, int smooth_iterations = 4);

}  // namespace bubble
