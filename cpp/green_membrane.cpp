#include "green_membrane.h"

#include <Eigen/Geometry>
#include <cmath>
#include <string>

#include "errors.h"

namespace bubble {

namespace {

// In-plane gradients of the three linear shape functions of a triangle (2 x 3, 1/m) in the
// frame i along x0 -> x1, j = k x i (k the unit normal), and its area (m^2).
Eigen::Matrix<double, 2, 3> triangle_gradients(const Eigen::Vector3d& x0, const Eigen::Vector3d& x1,
                                               const Eigen::Vector3d& x2, double& area) {
  const Eigen::Vector3d e1 = x1 - x0, e2 = x2 - x0;
  const Eigen::Vector3d c = e1.cross(e2);
  area = 0.5 * c.norm();
  const Eigen::Vector3d k = c / (2.0 * area);
  const Eigen::Vector3d i = e1 / e1.norm();
  const Eigen::Vector3d j = k.cross(i);
  const double a1 = e1.dot(i), b1 = e1.dot(j), a2 = e2.dot(i), b2 = e2.dot(j);
  const double det = a1 * b2 - a2 * b1;
  Eigen::Matrix<double, 2, 3> G;
  G(0, 1) = b2 / det;
  G(0, 2) = -b1 / det;
  G(1, 1) = -a2 / det;
  G(1, 2) = a1 / det;
  G.col(0) = -G.col(1) - G.col(2);
  return G;
}

}  // namespace

GreenMembrane::GreenMembrane(const Eigen::Ref<const RowMatrixX3d>& vertices,
                             const Eigen::Ref<const RowMatrixX3i>& triangles, double E, double nu,
                             double thickness, double tension, double p0)
    : X_(vertices), T_(triangles), nu_(nu), tension_(tension), p0_(p0) {
  const Eigen::Index n = X_.rows();
  require(n >= 3, "vertices: need at least 3 nodes, got " + std::to_string(n));
  require(T_.rows() >= 1, "triangles: need at least one triangle");
  require(X_.allFinite(), "vertices: contains NaN or inf");
  require(std::isfinite(E) && E > 0, "E must be finite and positive (Pa)");
  require(std::isfinite(nu) && nu > -1.0 && nu <= 0.5, "nu must be in (-1, 0.5]");
  require(std::isfinite(thickness) && thickness > 0, "thickness must be finite and positive");
  require(std::isfinite(tension), "tension must be finite");
  require(std::isfinite(p0), "p0 must be finite");
  require((T_.array() >= 0).all() && (T_.array() < n).all(),
          "triangles index a vertex outside 0.." + std::to_string(n - 1));
  c_ = E * thickness / (1.0 - nu * nu);
  G_.resize(static_cast<size_t>(T_.rows()));
  AG_.resize(G_.size());
  for (Eigen::Index t = 0; t < T_.rows(); ++t) {
    double area = 0;
    const auto G = triangle_gradients(X_.row(T_(t, 0)).transpose(), X_.row(T_(t, 1)).transpose(),
                                      X_.row(T_(t, 2)).transpose(), area);
    require(area > 0 && G.allFinite(), "triangle " + std::to_string(t) + " is degenerate");
    G_[static_cast<size_t>(t)] = G;
    AG_[static_cast<size_t>(t)] = area * G;
  }
  f0_ = internal(X_) - pressure(X_, p0_);
}

RowMatrixX3d GreenMembrane::external_forces(const Eigen::Ref<const RowMatrixX3d>& U,
                                            double dp) const {
  require(U.rows() == X_.rows(), "U must be N x 3 with N = " + std::to_string(X_.rows()));
  require(U.allFinite(), "U must be finite");
  require(std::isfinite(dp), "dp must be finite");
  const RowMatrixX3d x = X_ + U;
  return internal(x) - pressure(x, p0_ + dp) - f0_;
}

RowMatrixX3d GreenMembrane::internal(const RowMatrixX3d& x) const {
  RowMatrixX3d f = RowMatrixX3d::Zero(x.rows(), 3);
  for (Eigen::Index t = 0; t < T_.rows(); ++t) {
    Eigen::Matrix3d P;  // corners x coordinates
    for (int a = 0; a < 3; ++a) P.row(a) = x.row(T_(t, a));
    const Eigen::Matrix<double, 2, 3> F = G_[static_cast<size_t>(t)] * P;  // rows: dx/dxi_k
    const Eigen::Matrix2d E = 0.5 * (F * F.transpose() - Eigen::Matrix2d::Identity());
    Eigen::Matrix2d S;  // T0 I + C : E (plane stress, times the thickness)
    S(0, 0) = tension_ + c_ * (E(0, 0) + nu_ * E(1, 1));
    S(1, 1) = tension_ + c_ * (E(1, 1) + nu_ * E(0, 0));
    S(0, 1) = S(1, 0) = c_ * (1.0 - nu_) * E(0, 1);
    const Eigen::Matrix3d fa = AG_[static_cast<size_t>(t)].transpose() * (S * F);  // A F S g_a
    for (int a = 0; a < 3; ++a) f.row(T_(t, a)) += fa.row(a);
  }
  return f;
}

RowMatrixX3d GreenMembrane::pressure(const RowMatrixX3d& x, double p) const {
  RowMatrixX3d f = RowMatrixX3d::Zero(x.rows(), 3);
  for (Eigen::Index t = 0; t < T_.rows(); ++t) {
    const Eigen::RowVector3d x0 = x.row(T_(t, 0));
    const Eigen::RowVector3d c = (x.row(T_(t, 1)) - x0).cross(x.row(T_(t, 2)) - x0) * (p / 6.0);
    for (int a = 0; a < 3; ++a) f.row(T_(t, a)) += c;
  }
  return f;
}

}  // namespace bubble
