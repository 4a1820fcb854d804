// Z-buffer rasteriser for the simulator: depth and textured RGB of a triangle mesh seen by a
// pinhole camera (no distortion). Deterministic and single-threaded.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

namespace bubble {

using RowMatrixX3d = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
using RowMatrixX3i = Eigen::Matrix<int32_t, Eigen::Dynamic, 3, Eigen::RowMajor>;
using RowMatrixX2d = Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::RowMajor>;

struct RasterCamera {
  double fx = 0, fy = 0, cx = 0, cy = 0;
  int width = 0, height = 0;
};

// A texture in row-major H x W x C uint8 (C = 1 or 3), sampled bilinearly at texel coordinates
// (s right, t down; texel centres at integers), clamped at the border.
struct TextureView {
  const uint8_t* data = nullptr;
  int height = 0, width = 0, channels = 0;
};

struct RenderOptions {
  bool rgb = true;        // sample the texture (false: depth only)
  bool shading = true;    // Lambert factor from the view ray and interpolated vertex normals
  double ambient = 0.55;  // shade = ambient + (1 - ambient) * |cos|
  double near = 1e-4;     // triangles with a vertex closer than this (m) are skipped
};

struct RenderOutput {
  std::vector<float> depth;   // H * W, camera z (m), 0 where nothing is hit
  std::vector<uint8_t> rgb;   // H * W * 3 (empty when options.rgb is false)
  std::vector<int32_t> face;  // H * W triangle index, -1 where nothing is hit
};

// Renders triangles of `vertices` (camera frame, metres) with per-vertex texel coordinates
// `texcoords` (M x 2). Pixel (u, v) samples the ray through its centre (u, v), matching
// Camera.pixel_grid. Depth is exact for planar triangles (1/z interpolated linearly in the
// image), texture coordinates are perspective-correct.
RenderOutput rasterize(const Eigen::Ref<const RowMatrixX3d>& vertices,
                       const Eigen::Ref<const RowMatrixX3i>& triangles,
                       const Eigen::Ref<const RowMatrixX2d>& texcoords, const TextureView& texture,
                       const RasterCamera& camera, const RenderOptions& options);

}  // namespace bubble
