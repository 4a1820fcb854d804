#include "depth_fill.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "errors.h"

namespace bubble {
namespace {

// One coarse pixel from the valid fine pixels of its block (rows fd/fw, n_rows x n_cols from
// column fx), summed in row order.
inline void average_block(const float* const* fd, const float* const* fw, int n_rows, int fx,
                          int n_cols, float* cd, float* cw) {
  float sw = 0.f, sd = 0.f;
  for (int dy = 0; dy < n_rows; ++dy)
    for (int dx = 0; dx < n_cols; ++dx) {
      sw += fw[dy][fx + dx];
      sd += fw[dy][fx + dx] * fd[dy][fx + dx];
    }
  *cd = sw > 0.f ? sd / sw : 0.f;
  *cw = sw > 0.f ? sw / static_cast<float>(n_rows * n_cols) : 0.f;
}

// Push: the coarse level (d, w) of a fine one, into buffers reused from frame to frame.
void push(const cv::Mat& fd_img, const cv::Mat& fw_img, cv::Mat& cd_img, cv::Mat& cw_img) {
  const int h = (fd_img.rows + 1) / 2, wd = (fd_img.cols + 1) / 2;
  const int pairs = fd_img.cols / 2;  // blocks two fine columns wide
  cd_img.create(h, wd, CV_32F);
  cw_img.create(h, wd, CV_32F);
  for (int y = 0; y < h; ++y) {
    const int n_rows = std::min(2, fd_img.rows - 2 * y);
    const float* fd[2] = {fd_img.ptr<float>(2 * y), fd_img.ptr<float>(2 * y + n_rows - 1)};
    const float* fw[2] = {fw_img.ptr<float>(2 * y), fw_img.ptr<float>(2 * y + n_rows - 1)};
    float* cd = cd_img.ptr<float>(y);
    float* cw = cw_img.ptr<float>(y);
    if (n_rows == 2) {
      // The common block written out so that it vectorises (the same sums in the same order).
      for (int x = 0; x < pairs; ++x) {
        const float w00 = fw[0][2 * x], w01 = fw[0][2 * x + 1];
        const float w10 = fw[1][2 * x], w11 = fw[1][2 * x + 1];
        const float sw = w00 + w01 + w10 + w11;
        const float sd = w00 * fd[0][2 * x] + w01 * fd[0][2 * x + 1] + w10 * fd[1][2 * x] +
                         w11 * fd[1][2 * x + 1];
        cd[x] = sw > 0.f ? sd / sw : 0.f;
        cw[x] = sw > 0.f ? sw / 4.f : 0.f;
      }
    } else {
      for (int x = 0; x < pairs; ++x) average_block(fd, fw, 1, 2 * x, 2, cd + x, cw + x);
    }
    if (pairs < wd) average_block(fd, fw, n_rows, 2 * pairs, 1, cd + pairs, cw + pairs);
  }
}

// Where each fine pixel of a row (or column) samples the coarse level bilinearly: the two
// coarse pixels and the weight of the second (pixel centres aligned, clamped at the border).
struct Taps {
  std::vector<int> i0, i1;
  std::vector<float> a;
};

Taps taps(int fine, int coarse) {
  Taps t{std::vector<int>(fine), std::vector<int>(fine), std::vector<float>(fine)};
  for (int i = 0; i < fine; ++i) {
    const float c = std::min(std::max((i + 0.5f) * 0.5f - 0.5f, 0.f), coarse - 1.f);
    t.i0[i] = static_cast<int>(c);
    t.i1[i] = std::min(t.i0[i] + 1, coarse - 1);
    t.a[i] = c - t.i0[i];
  }
  return t;
}

// Pull: the holes (w = 0) of a fine level take the bilinear upsampling of the filled coarse one.
void pull(const cv::Mat& coarse, const cv::Mat& w, cv::Mat& d) {
  const Taps tx = taps(d.cols, coarse.cols), ty = taps(d.rows, coarse.rows);
  for (int y = 0; y < d.rows; ++y) {
    const float* r0 = coarse.ptr<float>(ty.i0[y]);
    const float* r1 = coarse.ptr<float>(ty.i1[y]);
    const float ay = ty.a[y];
    const float* wr = w.ptr<float>(y);
    float* dr = d.ptr<float>(y);
    for (int x = 0; x < d.cols; ++x) {
      if (wr[x] > 0.f) continue;
      const int x0 = tx.i0[x], x1 = tx.i1[x];
      const float ax = tx.a[x];
      dr[x] = (1 - ay) * ((1 - ax) * r0[x0] + ax * r0[x1]) + ay * ((1 - ax) * r1[x0] + ax * r1[x1]);
    }
  }
}

}  // namespace

void DepthFill::fill(const cv::Mat& depth, int smooth_iterations, int smooth_max_level) {
  require(depth.type() == CV_32F, "depth must be a float32 image");
  require(depth.rows > 0 && depth.cols > 0, "depth image is empty");
  require(smooth_iterations >= 0, "smooth_iterations must be >= 0");
  level_.create(depth.size(), CV_8U);
  level_.setTo(0);
  const long holes = load_base(depth);
  if (holes == 0) return;
  if (holes == static_cast<long>(depth.total())) {  // nothing to fill from: all zeros
    level_.setTo(255);
    return;
  }
  const int n_levels = build_pyramid();
  // Pull, from the coarsest level down to the image itself.
  for (int k = n_levels - 2; k >= 0; --k) pull(pyramid_[k + 1].d, pyramid_[k].w, pyramid_[k].d);
  mark_levels(n_levels, smooth_max_level);
  // Harmonic refinement inside the trusted holes (measured pixels fixed): Gauss-Seidel sweeps
  // in raster order.
  float* d0 = pyramid_.front().d.ptr<float>();
  for (int it = 0; it < smooth_iterations; ++it)
    for (const Cell& c : smooth_)
      d0[c.idx] = 0.25f * (d0[c.left] + d0[c.right] + d0[c.up] + d0[c.down]);
}

// The image as the pyramid's base: depth (0 in holes) and weight 1 / 0. Returns the holes.
long DepthFill::load_base(const cv::Mat& depth) {
  Level& base = pyramid_.front();
  base.d.create(depth.size(), CV_32F);
  base.w.create(depth.size(), CV_32F);
  constexpr float kInf = std::numeric_limits<float>::infinity();
  long holes = 0;
  for (int y = 0; y < depth.rows; ++y) {
    const float* src = depth.ptr<float>(y);
    float* d = base.d.ptr<float>(y);
    float* w = base.w.ptr<float>(y);
    int row_holes = 0;
    for (int x = 0; x < depth.cols; ++x) {
      const bool ok = src[x] > 0.f && src[x] < kInf;  // false for NaN as well
      d[x] = ok ? src[x] : 0.f;
      w[x] = ok ? 1.f : 0.f;
      row_holes += ok ? 0 : 1;
    }
    holes += row_holes;
  }
  return holes;
}

// Push down to a single pixel; returns the number of levels.
int DepthFill::build_pyramid() {
  int n = 1;
  for (; pyramid_[n - 1].d.rows > 1 || pyramid_[n - 1].d.cols > 1; ++n) {
    if (static_cast<int>(pyramid_.size()) == n) pyramid_.emplace_back();
    push(pyramid_[n - 1].d, pyramid_[n - 1].w, pyramid_[n].d, pyramid_[n].w);
  }
  return n;
}

// Provenance: the first level at which a pixel's block held measured depth, propagated from
// the coarsest level down (one lookup per pixel instead of a search up the pyramid). The
// base's holes at a level the sweeps trust are listed for them, in raster order.
void DepthFill::mark_levels(int n_levels, int smooth_max_level) {
  cv::Mat above;
  for (int k = n_levels - 1; k >= 1; --k) {
    const cv::Mat& w = pyramid_[k].w;
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
  const cv::Mat& w0 = pyramid_.front().w;
  const int rows = w0.rows, cols = w0.cols;
  smooth_.clear();
  for (int y = 0; y < rows; ++y) {
    const float* wr = w0.ptr<float>(y);
    uint8_t* lr = level_.ptr<uint8_t>(y);
    const uint8_t* ar = above.ptr<uint8_t>(y >> 1);
    for (int x = 0; x < cols; ++x) {
      if (wr[x] > 0.f) continue;
      lr[x] = ar[x >> 1];
      if (lr[x] > smooth_max_level) continue;
      const int idx = y * cols + x;
      smooth_.push_back({idx, x > 0 ? idx - 1 : idx, x < cols - 1 ? idx + 1 : idx,
                         y > 0 ? idx - cols : idx, y < rows - 1 ? idx + cols : idx});
    }
  }
}

void fill_depth(const cv::Mat& depth, cv::Mat& filled, cv::Mat& level, int smooth_iterations,
                int smooth_max_level) {
  DepthFill fill;
  fill.fill(depth, smooth_iterations, smooth_max_level);
  filled = fill.filled();
  level = fill.level();
}

}  // namespace bubble
