#include "sim_membrane.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <limits>

#include "errors.h"

namespace bubble {

namespace {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;
using Mat6 = Eigen::Matrix<double, 6, 6>;
using Vec6 = Eigen::Matrix<double, 6, 1>;
using Mat9 = Eigen::Matrix<double, 9, 9>;

Mat3 skew(const Vec3& v) {
  Mat3 m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

// Smallest |a x b|^2 accepted before a triangle counts as collapsed.
constexpr double kMinAreaRatio2 = 1e-12;

}  // namespace

SimMembrane::SimMembrane(const SimRowMatrixX3d& rest, const SimRowMatrixX3i& triangles,
                         const Eigen::VectorXi& fixed, double mu_t)
    : n_nodes_(static_cast<int>(rest.rows())), mu_t_(mu_t), tri_(triangles) {
  require(n_nodes_ >= 3, "rest mesh needs at least 3 nodes");
  require(triangles.rows() >= 1, "rest mesh needs at least one triangle");
  require(mu_t > 0 && std::isfinite(mu_t), "mu_t must be positive and finite");
  require(tri_.minCoeff() >= 0 && tri_.maxCoeff() < n_nodes_, "triangle index out of range");
  const int T = static_cast<int>(tri_.rows());
  std::vector<char> is_fixed(n_nodes_, 0);
  for (int k = 0; k < fixed.size(); ++k) {
    require(fixed[k] >= 0 && fixed[k] < n_nodes_, "fixed node index out of range");
    is_fixed[fixed[k]] = 1;
  }
  dof_.assign(n_nodes_, -1);
  for (int i = 0; i < n_nodes_; ++i) {
    if (!is_fixed[i]) {
      dof_[i] = n_free_;
      n_free_ += 3;
    }
  }
  require(n_free_ > 0, "every node is fixed");

  area0_.resize(T);
  coef_.resize(T, 6);
  for (int t = 0; t < T; ++t) {
    const Vec3 X0 = rest.row(tri_(t, 0)).transpose();
    const Vec3 E1 = rest.row(tri_(t, 1)).transpose() - X0;
    const Vec3 E2 = rest.row(tri_(t, 2)).transpose() - X0;
    const Vec3 nrm = E1.cross(E2);
    const double a2 = nrm.norm();
    require(a2 > 0, "degenerate rest triangle " + std::to_string(t));
    area0_[t] = 0.5 * a2;
    const Vec3 e1 = E1.normalized();
    const Vec3 e2 = (nrm / a2).cross(e1);
    Eigen::Matrix2d Dm;
    Dm << e1.dot(E1), e1.dot(E2), e2.dot(E1), e2.dot(E2);
    const Eigen::Matrix2d Di = Dm.inverse();
    // a = sum_i g_ia x_i, b = sum_i g_ib x_i.
    coef_(t, 2) = Di(0, 0);
    coef_(t, 4) = Di(1, 0);
    coef_(t, 0) = -(Di(0, 0) + Di(1, 0));
    coef_(t, 3) = Di(0, 1);
    coef_(t, 5) = Di(1, 1);
    coef_(t, 1) = -(Di(0, 1) + Di(1, 1));
  }

  // Fixed sparsity pattern (lower triangle) and the value slot of every contribution.
  std::vector<Eigen::Triplet<double>> trip;
  trip.reserve(static_cast<size_t>(T) * 45 + static_cast<size_t>(n_free_) * 6);
  auto add = [&](int r, int c) {
    if (r >= c) trip.emplace_back(r, c, 1.0);
  };
  for (int t = 0; t < T; ++t)
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        const int di = dof_[tri_(t, i)], dj = dof_[tri_(t, j)];
        if (di < 0 || dj < 0) continue;
        for (int p = 0; p < 3; ++p)
          for (int q = 0; q < 3; ++q) add(di + p, dj + q);
      }
  for (int i = 0; i < n_nodes_; ++i)
    if (dof_[i] >= 0)
      for (int p = 0; p < 3; ++p)
        for (int q = 0; q < 3; ++q) add(dof_[i] + p, dof_[i] + q);
  H_.resize(n_free_, n_free_);
  H_.setFromTriplets(trip.begin(), trip.end());
  H_.makeCompressed();
  const int* outer = H_.outerIndexPtr();
  const int* inner = H_.innerIndexPtr();
  auto slot = [&](int r, int c) -> int {
    if (r < c) return -1;
    const int* b = inner + outer[c];
    const int* e = inner + outer[c + 1];
    const int* it = std::lower_bound(b, e, r);
    return static_cast<int>(it - inner);
  };
  elem_slot_.assign(static_cast<size_t>(T) * 81, -1);
  for (int t = 0; t < T; ++t)
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        const int di = dof_[tri_(t, i)], dj = dof_[tri_(t, j)];
        if (di < 0 || dj < 0) continue;
        for (int p = 0; p < 3; ++p)
          for (int q = 0; q < 3; ++q)
            elem_slot_[static_cast<size_t>(t) * 81 + (3 * i + p) * 9 + 3 * j + q] =
                slot(di + p, dj + q);
      }
  node_slot_.assign(static_cast<size_t>(n_nodes_) * 9, -1);
  for (int i = 0; i < n_nodes_; ++i)
    if (dof_[i] >= 0)
      for (int p = 0; p < 3; ++p)
        for (int q = 0; q < 3; ++q)
          node_slot_[static_cast<size_t>(i) * 9 + 3 * p + q] = slot(dof_[i] + p, dof_[i] + q);
  diag_slot_.resize(n_free_);
  for (int r = 0; r < n_free_; ++r) diag_slot_[r] = slot(r, r);
}

double SimMembrane::energy(const SimRef3& x, SimRowMatrixX3d* grad) const {
  require(x.rows() == n_nodes_, "positions must be N x 3 with N the rest node count");
  if (grad) grad->setZero(n_nodes_, 3);
  const double inf = std::numeric_limits<double>::infinity();
  double total = 0.0;
  for (int t = 0; t < tri_.rows(); ++t) {
    const Vec3 x0 = x.row(tri_(t, 0)).transpose();
    const Vec3 x1 = x.row(tri_(t, 1)).transpose();
    const Vec3 x2 = x.row(tri_(t, 2)).transpose();
    const Vec3 a = coef_(t, 0) * x0 + coef_(t, 2) * x1 + coef_(t, 4) * x2;
    const Vec3 b = coef_(t, 1) * x0 + coef_(t, 3) * x1 + coef_(t, 5) * x2;
    const Vec3 c = a.cross(b);
    const double s = c.squaredNorm();
    if (!(s > kMinAreaRatio2)) return inf;
    const double k = 0.5 * mu_t_ * area0_[t];
    total += k * (a.squaredNorm() + b.squaredNorm() + 1.0 / s - 3.0);
    if (grad) {
      // d(1/s) = -ds / s^2 with ds/da = 2 b x c, ds/db = 2 c x a.
      const Vec3 ga = k * (2.0 * a - 2.0 * b.cross(c) / (s * s));
      const Vec3 gb = k * (2.0 * b - 2.0 * c.cross(a) / (s * s));
      for (int i = 0; i < 3; ++i)
        grad->row(tri_(t, i)) += (coef_(t, 2 * i) * ga + coef_(t, 2 * i + 1) * gb).transpose();
    }
  }
  return total;
}

double SimMembrane::volume(const SimRef3& x, SimRowMatrixX3d* grad) const {
  require(x.rows() == n_nodes_, "positions must be N x 3 with N the rest node count");
  if (grad) grad->setZero(n_nodes_, 3);
  double v = 0.0;
  for (int t = 0; t < tri_.rows(); ++t) {
    const Vec3 x0 = x.row(tri_(t, 0)).transpose();
    const Vec3 x1 = x.row(tri_(t, 1)).transpose();
    const Vec3 x2 = x.row(tri_(t, 2)).transpose();
    v += x0.dot(x1.cross(x2)) / 6.0;
    if (grad) {
      grad->row(tri_(t, 0)) += x1.cross(x2).transpose() / 6.0;
      grad->row(tri_(t, 1)) += x2.cross(x0).transpose() / 6.0;
      grad->row(tri_(t, 2)) += x0.cross(x1).transpose() / 6.0;
    }
  }
  return v;
}

bool SimMembrane::factorize(const SimRef3& x, double volume_scale, const SimRef9& blocks,
                            double shift, bool project) {
  assemble(x, volume_scale, blocks, shift, project);
  return factorize_assembled();
}

void SimMembrane::assemble(const SimRef3& x, double volume_scale, const SimRef9& blocks,
                           double shift, bool project) {
  require(x.rows() == n_nodes_, "positions must be N x 3 with N the rest node count");
  require(blocks.rows() == n_nodes_ || blocks.rows() == 0, "blocks must be N x 9 or empty");
  double* val = H_.valuePtr();
  std::fill(val, val + H_.nonZeros(), 0.0);
  Eigen::SelfAdjointEigenSolver<Mat6> eig;
  for (int t = 0; t < tri_.rows(); ++t) {
    const Vec3 x0 = x.row(tri_(t, 0)).transpose();
    const Vec3 x1 = x.row(tri_(t, 1)).transpose();
    const Vec3 x2 = x.row(tri_(t, 2)).transpose();
    const Vec3 a = coef_(t, 0) * x0 + coef_(t, 2) * x1 + coef_(t, 4) * x2;
    const Vec3 b = coef_(t, 1) * x0 + coef_(t, 3) * x1 + coef_(t, 5) * x2;
    const Vec3 c = a.cross(b);
    const double s = std::max(c.squaredNorm(), kMinAreaRatio2);
    // Hessian of s = |a x b|^2 in (a, b): 2 J^T J + [[0, -2[c]x], [2[c]x, 0]].
    Eigen::Matrix<double, 3, 6> J;
    J.leftCols<3>() = -skew(b);
    J.rightCols<3>() = skew(a);
    Mat6 Hs = 2.0 * J.transpose() * J;
    Hs.block<3, 3>(0, 3) += -2.0 * skew(c);
    Hs.block<3, 3>(3, 0) += 2.0 * skew(c);
    Vec6 gs;
    gs.head<3>() = 2.0 * b.cross(c);
    gs.tail<3>() = 2.0 * c.cross(a);
    const double k = 0.5 * mu_t_ * area0_[t];
    Mat6 HF = 2.0 / (s * s * s) * gs * gs.transpose() - Hs / (s * s);
    HF.diagonal().array() += 2.0;
    HF *= k;
    if (project) {
      eig.compute(HF);
      if (eig.eigenvalues()[0] < 0.0) {
        const Vec6 lam = eig.eigenvalues().cwiseMax(0.0);
        HF = eig.eigenvectors() * lam.asDiagonal() * eig.eigenvectors().transpose();
      }
    }
    Mat9 K;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        const double ia = coef_(t, 2 * i), ib = coef_(t, 2 * i + 1);
        const double ja = coef_(t, 2 * j), jb = coef_(t, 2 * j + 1);
        K.block<3, 3>(3 * i, 3 * j) =
            ia * ja * HF.block<3, 3>(0, 0) + ia * jb * HF.block<3, 3>(0, 3) +
            ib * ja * HF.block<3, 3>(3, 0) + ib * jb * HF.block<3, 3>(3, 3);
      }
    if (volume_scale != 0.0) {
      const double f = volume_scale / 6.0;
      const Mat3 H01 = -f * skew(x2), H12 = -f * skew(x0), H20 = -f * skew(x1);
      K.block<3, 3>(0, 3) += H01;
      K.block<3, 3>(3, 0) += H01.transpose();
      K.block<3, 3>(3, 6) += H12;
      K.block<3, 3>(6, 3) += H12.transpose();
      K.block<3, 3>(6, 0) += H20;
      K.block<3, 3>(0, 6) += H20.transpose();
    }
    const int* sl = elem_slot_.data() + static_cast<size_t>(t) * 81;
    for (int r = 0; r < 9; ++r)
      for (int q = 0; q < 9; ++q) {
        const int s_idx = sl[r * 9 + q];
        if (s_idx >= 0) val[s_idx] += K(r, q);
      }
  }
  if (blocks.rows() == n_nodes_) {
    for (int i = 0; i < n_nodes_; ++i) {
      const int* sl = node_slot_.data() + static_cast<size_t>(i) * 9;
      for (int e = 0; e < 9; ++e)
        if (sl[e] >= 0) val[sl[e]] += blocks(i, e);
    }
  }
  if (shift != 0.0)
    for (int r = 0; r < n_free_; ++r) val[diag_slot_[r]] += shift;
  assembled_ = true;
}

bool SimMembrane::factorize_assembled() {
  require(assembled_, "nothing assembled yet");
  if (!analyzed_) {
    ldlt_.analyzePattern(H_);
    analyzed_ = true;
  }
  ldlt_.factorize(H_);
  factorized_ = ldlt_.info() == Eigen::Success;
  return factorized_;
}

SimRowMatrixX3d SimMembrane::multiply(const SimRef3& v) const {
  require(assembled_, "nothing assembled yet");
  require(v.rows() == n_nodes_, "v must be N x 3");
  Eigen::VectorXd r(n_free_);
  for (int i = 0; i < n_nodes_; ++i)
    if (dof_[i] >= 0) r.segment<3>(dof_[i]) = v.row(i).transpose();
  const Eigen::VectorXd y = H_.selfadjointView<Eigen::Lower>() * r;
  SimRowMatrixX3d out = SimRowMatrixX3d::Zero(n_nodes_, 3);
  for (int i = 0; i < n_nodes_; ++i)
    if (dof_[i] >= 0) out.row(i) = y.segment<3>(dof_[i]).transpose();
  return out;
}

long SimMembrane::factor_nnz() const {
  require(factorized_, "no successful factorisation yet");
  return static_cast<long>(ldlt_.matrixL().nestedExpression().nonZeros());
}

int SimMembrane::nonpositive_pivots() const {
  require(factorized_, "no successful factorisation yet");
  return static_cast<int>((ldlt_.vectorD().array() <= 0.0).count());
}

SimRowMatrixX3d SimMembrane::solve(const SimRef3& rhs) const {
  require(factorized_, "solve called without a successful factorisation");
  require(rhs.rows() == n_nodes_, "rhs must be N x 3");
  Eigen::VectorXd r(n_free_);
  for (int i = 0; i < n_nodes_; ++i)
    if (dof_[i] >= 0) r.segment<3>(dof_[i]) = rhs.row(i).transpose();
  const Eigen::VectorXd y = ldlt_.solve(r);
  SimRowMatrixX3d out = SimRowMatrixX3d::Zero(n_nodes_, 3);
  for (int i = 0; i < n_nodes_; ++i)
    if (dof_[i] >= 0) out.row(i) = y.segment<3>(dof_[i]).transpose();
  return out;
}

}  // namespace bubble
