#include "depth_fill.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "errors.h"

namespace bubble {
namespace {

struct Level {
  cv::Mat d;  // CV_32F depth, valid where w > 0
  cv::Mat w;  // CV_32F weight (number of valid source pixels, normalised to the block)
};

Level push(const Level& fine) {
  const int h = (fine.d.rows + 1) / 2, wd = (fine.d.cols + 1) / 2;
  Level c{cv::Mat::zeros(h, wd, CV_32F), cv::Mat::zeros(h, wd, CV_32F)};
  for (int y = 0; y < h; ++y) {
    float* cd = c.d.ptr<float>(y);
    float* cw = c.w.ptr<float>(y);
    for (int x = 0; x < wd; ++x) {
      float sw = 0.f, sd = 0.f;
      int n = 0;
      for (int dy = 0; dy < 2; ++dy) {
        const int fy = 2 * y + dy;
        if (fy >= fine.d.rows) continue;
        const float* fd = fine.d.ptr<float>(fy);
        const float* fw = fine.w.ptr<float>(fy);
        for (int dx = 0; dx < 2; ++dx) {
          const int fx = 2 * x + dx;
          if (fx >= fine.d.cols) continue;
          ++n;
          sw += fw[fx];
          sd += fw[fx] * fd[fx];
        }
      }
      if (sw > 0.f) {
        cd[x] = sd / sw;
        cw[x] = sw / static_cast<float>(n);
      }
    }
  }
  return c;
}

// Bilinear sample of a fully filled coarse level at the position of fine pixel (x, y).
inline float upsample(const cv::Mat& coarse, int x, int y) {
  const float cx = std::min(std::max((x + 0.5f) * 0.5f - 0.5f, 0.f), coarse.cols - 1.f);
  const float cy = std::min(std::max((y + 0.5f) * 0.5f - 0.5f, 0.f), coarse.rows - 1.f);
  const int x0 = static_cast<int>(cx), y0 = static_cast<int>(cy);
  const int x1 = std::min(x0 + 1, coarse.cols - 1), y1 = std::min(y0 + 1, coarse.rows - 1);
  const float ax = cx - x0, ay = cy - y0;
  const float* r0 = coarse.ptr<float>(y0);
  const float* r1 = coarse.ptr<float>(y1);
  return (1 - ay) * ((1 - ax) * r0[x0] + ax * r0[x1]) + ay * ((1 - ax) * r1[x0] + ax * r1[x1]);
}

}  // namespace

void fill_depth(const cv::Mat& depth, cv::Mat& filled, cv::Mat& level, int smooth_iterations,
                int smooth_max_level) {
  require(depth.type() == CV_32F, "depth must be a float32 image");
  require(depth.rows > 0 && depth.cols > 0, "depth image is empty");
  require(smooth_iterations >= 0, "smooth_iterations must be >= 0");
  const int rows = depth.rows, cols = depth.cols;
  Level base{cv::Mat(depth.size(), CV_32F), cv::Mat(depth.size(), CV_32F)};
  level.create(depth.size(), CV_8U);
  std::vector<int> holes;
  for (int y = 0; y < rows; ++y) {
    const float* src = depth.ptr<float>(y);
    float* d = base.d.ptr<float>(y);
    float* w = base.w.ptr<float>(y);
    uint8_t* l = level.ptr<uint8_t>(y);
    for (int x = 0; x < cols; ++x) {
      const bool ok = std::isfinite(src[x]) && src[x] > 0.f;
      d[x] = ok ? src[x] : 0.f;
      w[x] = ok ? 1.f : 0.f;
      l[x] = 0;
      if (!ok) holes.push_back(y * cols + x);
    }
  }
  if (holes.size() == static_cast<size_t>(rows) * cols) {
    filled = cv::Mat::zeros(depth.size(), CV_32F);
    level.setTo(255);
    return;
  }
  if (holes.empty()) {
    filled = base.d;
    return;
  }
  std::vector<Level> pyr;
  pyr.push_back(base);
  while (pyr.back().d.rows > 1 || pyr.back().d.cols > 1) pyr.push_back(push(pyr.back()));
  // Pull: fill each coarser level's holes from the (already filled) level above.
  for (int k = static_cast<int>(pyr.size()) - 2; k >= 1; --k) {
    const cv::Mat& coarse = pyr[k + 1].d;
    Level& L = pyr[k];
    for (int y = 0; y < L.d.rows; ++y) {
      float* d = L.d.ptr<float>(y);
      const float* w = L.w.ptr<float>(y);
      for (int x = 0; x < L.d.cols; ++x)
        if (w[x] <= 0.f) d[x] = upsample(coarse, x, y);
    }
  }
  // Provenance: the first level at which a pixel's block held measured depth, propagated from
  // the coarsest level down (one lookup per pixel instead of a search up the pyramid).
  const int n_levels = static_cast<int>(pyr.size());
  cv::Mat above;
  for (int k = n_levels - 1; k >= 1; --k) {
    const cv::Mat& w = pyr[k].w;
    cv::Mat here(w.size(), CV_8U);
    for (int y = 0; y < w.rows; ++y) {
      const float* wr = w.ptr<float>(y);
      uint8_t* hr = here.ptr<uint8_t>(y);
      const uint8_t* ar = above.empty() ? nullptr : above.ptr<uint8_t>(y >> 1);
      for (int x = 0; x < w.cols; ++x)
        hr[x] = wr[x] > 0.f ? static_cast<uint8_t>(std::min(k, 254)) : (ar ? ar[x >> 1] : 254);
    }
    above = here;
  }
  float* d0 = pyr[0].d.ptr<float>();
  uint8_t* l0 = level.ptr<uint8_t>();
  for (const int idx : holes) {
    const int y = idx / cols, x = idx - y * cols;
    d0[idx] = upsample(pyr[1].d, x, y);
    l0[idx] = above.at<uint8_t>(y >> 1, x >> 1);
  }
  filled = pyr[0].d;
  // Harmonic refinement inside holes (measured pixels fixed): Gauss-Seidel sweeps, only where
  // the fill is trusted at all (large holes, e.g. the background, are flagged by their level).
  std::vector<int> smooth;
  smooth.reserve(holes.size());
  for (const int idx : holes)
    if (l0[idx] <= smooth_max_level) smooth.push_back(idx);
  for (int it = 0; it < smooth_iterations; ++it) {
    for (const int idx : smooth) {
      const int y = idx / cols, x = idx - y * cols;
      const float left = d0[x > 0 ? idx - 1 : idx], right = d0[x < cols - 1 ? idx + 1 : idx];
      const float up = d0[y > 0 ? idx - cols : idx], down = d0[y < rows - 1 ? idx + cols : idx];
      d0[idx] = 0.25f * (left + right + up + down);
    }
  }
}

}  // namespace bubble
