#include "rasterizer.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>

#include "errors.h"

namespace bubble {
namespace {

inline double edge(double ax, double ay, double bx, double by, double px, double py) {
  return (bx - ax) * (py - ay) - (by - ay) * (px - ax);
}

// Bilinear sample of all channels at texel coordinates (s, t), clamped to the border; writes
// 3 values (a grey texture is replicated).
inline void sample_rgb(const TextureView& tex, double s, double t, double out[3]) {
  const double smax = tex.width - 1, tmax = tex.height - 1;
  s = s < 0 ? 0 : (s > smax ? smax : s);
  t = t < 0 ? 0 : (t > tmax ? tmax : t);
  int s0 = static_cast<int>(s), t0 = static_cast<int>(t);
  if (s0 > tex.width - 2) s0 = tex.width > 1 ? tex.width - 2 : 0;
  if (t0 > tex.height - 2) t0 = tex.height > 1 ? tex.height - 2 : 0;
  const int s1 = tex.width > 1 ? s0 + 1 : s0, t1 = tex.height > 1 ? t0 + 1 : t0;
  const double fs = s - s0, ft = t - t0;
  const double w00 = (1 - ft) * (1 - fs), w01 = (1 - ft) * fs, w10 = ft * (1 - fs), w11 = ft * fs;
  const int C = tex.channels;
  const uint8_t* p00 = tex.data + (static_cast<size_t>(t0) * tex.width + s0) * C;
  const uint8_t* p01 = tex.data + (static_cast<size_t>(t0) * tex.width + s1) * C;
  const uint8_t* p10 = tex.data + (static_cast<size_t>(t1) * tex.width + s0) * C;
  const uint8_t* p11 = tex.data + (static_cast<size_t>(t1) * tex.width + s1) * C;
  for (int c = 0; c < 3; ++c) {
    const int k = C == 3 ? c : 0;
    out[c] = w00 * p00[k] + w01 * p01[k] + w10 * p10[k] + w11 * p11[k];
  }
}

}  // namespace

RenderOutput rasterize(const Eigen::Ref<const RowMatrixX3d>& vertices,
                       const Eigen::Ref<const RowMatrixX3i>& triangles,
                       const Eigen::Ref<const RowMatrixX2d>& texcoords, const TextureView& texture,
                       const RasterCamera& cam, const RenderOptions& options) {
  const Eigen::Index M = vertices.rows();
  require(cam.width > 0 && cam.height > 0, "rasterize: image size must be positive");
  require(cam.fx > 0 && cam.fy > 0, "rasterize: focal lengths must be positive");
  require(!options.rgb || texcoords.rows() == M,
          "rasterize: texcoords must have one row per vertex");
  require(!options.rgb || (texture.data != nullptr && texture.width > 0 && texture.height > 0 &&
                           (texture.channels == 1 || texture.channels == 3)),
          "rasterize: texture must be a non-empty H x W (x 1 or 3) uint8 image");
  require(vertices.allFinite(), "rasterize: vertices must be finite");
  for (Eigen::Index t = 0; t < triangles.rows(); ++t)
    for (int k = 0; k < 3; ++k)
      require(triangles(t, k) >= 0 && triangles(t, k) < M,
              "rasterize: triangle " + std::to_string(t) + " indexes a vertex out of range");

  const int W = cam.width, H = cam.height;
  const size_t P = static_cast<size_t>(W) * H;
  RenderOutput out;
  out.depth.assign(P, 0.0f);
  out.face.assign(P, -1);
  std::vector<double> inv_z(P, 0.0);  // z-buffer on 1/z (larger = nearer)
  std::vector<double> bary(options.rgb ? P * 3 : 0, 0.0);

  // Projected vertices.
  Eigen::ArrayXd px(M), py(M), iz(M);
  for (Eigen::Index i = 0; i < M; ++i) {
    const double z = vertices(i, 2);
    iz[i] = z > 0 ? 1.0 / z : 0.0;
    px[i] = cam.fx * vertices(i, 0) * iz[i] + cam.cx;
    py[i] = cam.fy * vertices(i, 1) * iz[i] + cam.cy;
  }

  for (Eigen::Index t = 0; t < triangles.rows(); ++t) {
    const int a = triangles(t, 0), b = triangles(t, 1), c = triangles(t, 2);
    if (vertices(a, 2) < options.near || vertices(b, 2) < options.near ||
        vertices(c, 2) < options.near)
      continue;
    const double area = edge(px[a], py[a], px[b], py[b], px[c], py[c]);
    if (std::abs(area) < 1e-12) continue;
    const double xmin = std::min({px[a], px[b], px[c]}), xmax = std::max({px[a], px[b], px[c]});
    const double ymin = std::min({py[a], py[b], py[c]}), ymax = std::max({py[a], py[b], py[c]});
    const int u0 = std::max(0, static_cast<int>(std::ceil(xmin)));
    const int u1 = std::min(W - 1, static_cast<int>(std::floor(xmax)));
    const int v0 = std::max(0, static_cast<int>(std::ceil(ymin)));
    const int v1 = std::min(H - 1, static_cast<int>(std::floor(ymax)));
    if (u0 > u1 || v0 > v1) continue;
    const double inv_area = 1.0 / area;
    for (int v = v0; v <= v1; ++v) {
      for (int u = u0; u <= u1; ++u) {
        // Screen-space barycentrics; the sign test is orientation independent because both
        // faces are visible (the camera sees the membrane's inner side).
        double w0 = edge(px[b], py[b], px[c], py[c], u, v) * inv_area;
        double w1 = edge(px[c], py[c], px[a], py[a], u, v) * inv_area;
        double w2 = 1.0 - w0 - w1;
        const double eps = -1e-12;
        if (w0 < eps || w1 < eps || w2 < eps) continue;
        const double izp = w0 * iz[a] + w1 * iz[b] + w2 * iz[c];
        const size_t p = static_cast<size_t>(v) * W + u;
        if (izp <= inv_z[p]) continue;
        inv_z[p] = izp;
        out.face[p] = static_cast<int32_t>(t);
        if (options.rgb) {
          // Perspective-correct weights.
          const double z = 1.0 / izp;
          bary[3 * p] = w0 * iz[a] * z;
          bary[3 * p + 1] = w1 * iz[b] * z;
          bary[3 * p + 2] = w2 * iz[c] * z;
        }
      }
    }
  }
  for (size_t p = 0; p < P; ++p)
    if (out.face[p] >= 0) out.depth[p] = static_cast<float>(1.0 / inv_z[p]);
  if (!options.rgb) return out;

  // Area-weighted vertex normals for shading.
  RowMatrixX3d normals = RowMatrixX3d::Zero(M, 3);
  if (options.shading) {
    for (Eigen::Index t = 0; t < triangles.rows(); ++t) {
      const int a = triangles(t, 0), b = triangles(t, 1), c = triangles(t, 2);
      const Eigen::RowVector3d n =
          (vertices.row(b) - vertices.row(a)).cross(vertices.row(c) - vertices.row(a));
      normals.row(a) += n;
      normals.row(b) += n;
      normals.row(c) += n;
    }
    for (Eigen::Index i = 0; i < M; ++i) {
      const double len = normals.row(i).norm();
      if (len > 0) normals.row(i) /= len;
    }
  }
  out.rgb.assign(P * 3, 0);
  for (int v = 0; v < H; ++v) {
    for (int u = 0; u < W; ++u) {
      const size_t p = static_cast<size_t>(v) * W + u;
      const int32_t t = out.face[p];
      if (t < 0) continue;
      const int a = triangles(t, 0), b = triangles(t, 1), c = triangles(t, 2);
      const double l0 = bary[3 * p], l1 = bary[3 * p + 1], l2 = bary[3 * p + 2];
      const double s = l0 * texcoords(a, 0) + l1 * texcoords(b, 0) + l2 * texcoords(c, 0);
      const double tt = l0 * texcoords(a, 1) + l1 * texcoords(b, 1) + l2 * texcoords(c, 1);
      double shade = 1.0;
      if (options.shading) {
        double n[3], nn = 0;
        for (int k = 0; k < 3; ++k) {
          n[k] = l0 * normals(a, k) + l1 * normals(b, k) + l2 * normals(c, k);
          nn += n[k] * n[k];
        }
        const double rx = (u - cam.cx) / cam.fx, ry = (v - cam.cy) / cam.fy;
        const double rr = rx * rx + ry * ry + 1.0;
        const double dot = n[0] * rx + n[1] * ry + n[2];
        const double cosine = nn > 0 ? std::abs(dot) / std::sqrt(nn * rr) : 1.0;
        shade = options.ambient + (1.0 - options.ambient) * cosine;
      }
      double rgb[3];
      sample_rgb(texture, s, tt, rgb);
      for (int ch = 0; ch < 3; ++ch) {
        const double val = rgb[ch] * shade + 0.5;
        out.rgb[3 * p + ch] = static_cast<uint8_t>(val < 0 ? 0 : (val > 255 ? 255 : val));
      }
    }
  }
  return out;
}

}  // namespace bubble
