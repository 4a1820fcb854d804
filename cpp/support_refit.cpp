#include "support_refit.h"

#include <Eigen/Core>
#include <Eigen/SparseCholesky>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <string>
#include <utility>
#include <vector>

#include "errors.h"

namespace bubble {

namespace {
// The dense support form costs about s^3 (its Cholesky), the sparse constraint form about
// c^1.5 (a sparse Cholesky on a surface mesh), for support and constraint dofs s, c. Measured
// per linear refit on a demo frame, LAPACK's dense Cholesky (dense_cholesky.h), supports
// grown from the middle: the two forms cost the same at s^3 / c^1.5 = 1.1e4 on 390 nodes (1.8
// against 1.7 ms) and 1.2e4 on 749 (8.2 against 7.7 ms); with Eigen's Cholesky the crossover
// was at 5e3. The switch lands at a support of about 45 % of the free dofs.
bool dense_is_cheaper(size_t s, size_t c) {
  const double sd = static_cast<double>(s), cd = static_cast<double>(c);
  return sd * sd * sd < 1e4 * cd * std::sqrt(cd);
}

}  // namespace

SupportRefit::SupportRefit(const SparseMatrixd& K, const Eigen::Ref<const RowMatrixX3d>& an,
                           const Eigen::Ref<const Eigen::VectorXi>& boundary) {
  const auto t0 = std::chrono::steady_clock::now();
  n_ = static_cast<int>(an.rows());
  require(n_ >= 1, "area_normals must have at least one row");
  require(K.rows() == 3 * n_ && K.cols() == 3 * n_, "K must be 3N x 3N");
  require(an.allFinite(), "area_normals must be finite");
  slot_ = Eigen::VectorXi::Zero(n_);
  for (Eigen::Index i = 0; i < boundary.size(); ++i) {
    require(boundary(i) >= 0 && boundary(i) < n_, "boundary index out of range");
    slot_(boundary(i)) = -1;
  }
  free_.resize(n_);
  nf_ = 0;
  for (int i = 0; i < n_; ++i)
    if (slot_(i) == 0) {
      slot_(i) = nf_;
      free_(nf_++) = i;
    }
  free_.conservativeResize(nf_);
  require(nf_ >= 1, "no free node");
  K_ = K;
  K_.makeCompressed();
  an_ = an;

  // K_ff: free rows and columns.
  std::vector<Eigen::Triplet<double>> trip;
  trip.reserve(static_cast<size_t>(K_.nonZeros()));
  for (Eigen::Index c = 0; c < K_.outerSize(); ++c) {
    const int jc = slot_(static_cast<int>(c / 3));
    if (jc < 0) continue;
    for (SparseMatrixd::InnerIterator it(K_, c); it; ++it) {
      const int ir = slot_(static_cast<int>(it.row() / 3));
      if (ir < 0) continue;
      trip.emplace_back(3 * ir + static_cast<int>(it.row() % 3), 3 * jc + static_cast<int>(c % 3),
                        it.value());
    }
  }
  const int m = 3 * nf_;
  SparseMatrixd Kff(m, m);
  Kff.setFromTriplets(trip.begin(), trip.end());
  Kff.makeCompressed();
  KffT_ = Kff.transpose();
  KKt_ = (Kff * KffT_).pruned();
  try {
    kkt_factor_ = std::make_shared<const BlockLDLT>(KKt_);
  } catch (const InputError&) {
    throw InputError("K_ff is singular: the refit needs a clamped rim");
  }

  // H = (K_ff K_ff^T)^{-1} from the dense Cholesky factor of K_ff K_ff^T (LAPACK dpotrf,
  // dpotri: m^3 flops). Forming it as G^T G with G = K_ff^{-1}, solved column by column with
  // a sparse LU of K_ff, took 8x as long (1.7 s against 0.2 s at 749 nodes; K_ff's condition number
  // is about 2e3 there, so squaring it costs no digits that matter: the two agree to 2e-12).
  H_ = spd_inverse(Eigen::MatrixXd(KKt_));
  setup_ms_ =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

RowMatrixX3d SupportRefit::refit(
    const Eigen::Ref<const RowMatrixX3d>& U, double dp,
    const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support) const {
  require(support.size() == n_, "support must have N = " + std::to_string(n_) + " entries");
  return refit(U, dp, Factored(*this, support));
}

RowMatrixX3d SupportRefit::refit(const Eigen::Ref<const RowMatrixX3d>& U, double dp,
                                 const Factored& system) const {
  require(U.rows() == n_, "U must be N x 3 with N = " + std::to_string(n_));
  require(U.allFinite(), "U must be finite");
  require(std::isfinite(dp), "dp must be finite");
  const RowMatrixX3d U0 = rim_zeroed(U);
  return U0 + shifted_correction(U0, RowMatrixX3d::Zero(n_, 3), dp, system);
}

RowMatrixX3d SupportRefit::shifted_correction(const RowMatrixX3d& U, const RowMatrixX3d& q,
                                              double dp, const Factored& system) const {
  const Eigen::VectorXd x = system.solve(raw_forces(rim_zeroed(U), dp) + free_rows(q));
  RowMatrixX3d X = RowMatrixX3d::Zero(n_, 3);
  for (int j = 0; j < nf_; ++j) X.row(free_(j)) = x.segment<3>(3 * j).transpose();
  return X;
}

RowMatrixX3d SupportRefit::rim_zeroed(const RowMatrixX3d& U) const {
  RowMatrixX3d U0 = U;
  for (int i = 0; i < n_; ++i)
    if (slot_(i) < 0) U0.row(i).setZero();
  return U0;
}

Eigen::VectorXd SupportRefit::raw_forces(const RowMatrixX3d& U0, double dp) const {
  return free_rows(linear_forces(U0, dp));
}

Eigen::VectorXd SupportRefit::free_rows(const RowMatrixX3d& A) const {
  Eigen::VectorXd a(3 * nf_);
  for (int j = 0; j < nf_; ++j) a.segment<3>(3 * j) = A.row(free_(j)).transpose();
  return a;
}

RowMatrixX3d SupportRefit::linear_forces(const RowMatrixX3d& W, double dp) const {
  RowMatrixX3d F(n_, 3);
  Eigen::Map<Eigen::VectorXd>(F.data(), 3 * n_).noalias() =
      K_ * Eigen::Map<const Eigen::VectorXd>(W.data(), 3 * n_);
  F -= dp * an_;
  return F;
}

SupportRefit::Factored::Factored(
    const SupportRefit& owner,
    const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support)
    : owner_(owner) {
  require(support.size() == owner.n_,
          "support must have N = " + std::to_string(owner.n_) + " entries");
  for (int j = 0; j < owner.nf_; ++j)
    for (int d = 0; d < 3; ++d) (support(owner.free_(j)) ? sd_ : cd_).push_back(3 * j + d);
  dense_ = dense_is_cheaper(sd_.size(), cd_.size());
  if (dense_) {
    const int s = static_cast<int>(sd_.size());
    Eigen::MatrixXd Hss(s, s);   // lower triangle only: the factorization reads no more
    for (int b = 0; b < s; ++b)  // down each column: both matrices are column-major
      for (int a = b; a < s; ++a) Hss(a, b) = owner.H_(sd_[a], sd_[b]);
    if (s > 0) hss_.compute(std::move(Hss));
    return;
  }
  const int m = 3 * owner.nf_, c = static_cast<int>(cd_.size());
  std::vector<int> pos(m, -1);
  for (int a = 0; a < c; ++a) pos[cd_[a]] = a;
  std::vector<Eigen::Triplet<double>> trip;
  for (int a = 0; a < c; ++a)
    for (SparseMatrixd::InnerIterator it(owner.KKt_, cd_[a]); it; ++it)
      if (pos[it.row()] >= 0) trip.emplace_back(pos[it.row()], a, it.value());
  SparseMatrixd Mcc(c, c);
  Mcc.setFromTriplets(trip.begin(), trip.end());
  mcc_.compute(Mcc);
  require(mcc_.info() == Eigen::Success, "refit: the constraint system is not positive definite");
}

// Dense form: f_S from H_SS f_S = (H F_raw)_S, then x = K_ff^{-1} (f - F_raw).
// Sparse form: x = -K_C^T lambda with (K_ff K_ff^T)_CC lambda = F_raw,C, the minimum-norm x
// whose forces F_raw + K_ff x vanish on C.
Eigen::VectorXd SupportRefit::Factored::solve(const Eigen::VectorXd& fraw) const {
  const SupportRefit& o = owner_;
  if (dense_) {
    const int s = static_cast<int>(sd_.size());
    Eigen::VectorXd f = Eigen::VectorXd::Zero(3 * o.nf_);
    if (s > 0) {
      Eigen::VectorXd hf, work;
      o.kkt_factor_->solve(fraw, hf, work);  // H fraw
      Eigen::VectorXd rhs(s);
      for (int a = 0; a < s; ++a) rhs(a) = hf(sd_[a]);
      const Eigen::VectorXd fs = hss_.solve(rhs);
      for (int a = 0; a < s; ++a) f(sd_[a]) = fs(a);
    }
    // x = K_ff^{-1} (f - fraw) = K_ff^T (K_ff K_ff^T)^{-1} (f - fraw): the same block factor
    Eigen::VectorXd y, work;
    o.kkt_factor_->solve(f - fraw, y, work);
    return o.KffT_ * y;
  }
  const int c = static_cast<int>(cd_.size());
  if (c == 0) return Eigen::VectorXd::Zero(3 * o.nf_);
  Eigen::VectorXd rhs(c);
  for (int a = 0; a < c; ++a) rhs(a) = fraw(cd_[a]);
  const Eigen::VectorXd lambda = mcc_.solve(rhs);
  Eigen::VectorXd lam = Eigen::VectorXd::Zero(3 * o.nf_);
  for (int a = 0; a < c; ++a) lam(cd_[a]) = lambda(a);
  return -(o.KffT_ * lam);
}

}  // namespace bubble
