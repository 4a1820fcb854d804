#include "support_refit.h"

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <chrono>
#include <cmath>
#include <string>
#include <vector>

#include "errors.h"

namespace bubble {

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
  lu_.analyzePattern(Kff);
  lu_.factorize(Kff);
  require(lu_.info() == Eigen::Success, "K_ff is singular: the refit needs a clamped rim");

  // H = G^T G with G = K_ff^{-1}: the sparse LU solves the identity column by column (cheap:
  // the factor is sparse), then a symmetric rank update forms H (half a dense product).
  const Eigen::MatrixXd G = lu_.solve(Eigen::MatrixXd::Identity(m, m));
  require(G.allFinite(), "K_ff is singular: the refit needs a clamped rim");
  H_.setZero(m, m);
  H_.selfadjointView<Eigen::Lower>().rankUpdate(G.transpose());
  H_.triangularView<Eigen::StrictlyUpper>() = H_.transpose();
  setup_ms_ =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

RowMatrixX3d SupportRefit::refit(
    const Eigen::Ref<const RowMatrixX3d>& U, double dp,
    const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support) const {
  require(U.rows() == n_, "U must be N x 3 with N = " + std::to_string(n_));
  require(support.size() == n_, "support must have N = " + std::to_string(n_) + " entries");
  require(U.allFinite(), "U must be finite");
  require(std::isfinite(dp), "dp must be finite");

  RowMatrixX3d U0 = U;
  for (int i = 0; i < n_; ++i)
    if (slot_(i) < 0) U0.row(i).setZero();
  const Eigen::Map<const Eigen::VectorXd> u0(U0.data(), 3 * n_);
  const Eigen::VectorXd ku = K_ * u0;
  const int m = 3 * nf_;
  Eigen::VectorXd fraw(m);
  for (int j = 0; j < nf_; ++j)
    for (int d = 0; d < 3; ++d) fraw(3 * j + d) = ku(3 * free_(j) + d) - dp * an_(free_(j), d);

  std::vector<int> sd;  // support dofs (free numbering)
  for (int j = 0; j < nf_; ++j)
    if (support(free_(j)))
      for (int d = 0; d < 3; ++d) sd.push_back(3 * j + d);
  const int s = static_cast<int>(sd.size());
  Eigen::VectorXd f = Eigen::VectorXd::Zero(m);
  if (s > 0) {
    Eigen::MatrixXd Hss(s, s);
    Eigen::VectorXd rhs(s);
    for (int a = 0; a < s; ++a) {
      rhs(a) = H_.col(sd[a]).dot(fraw);  // H symmetric: row sd[a] = column sd[a]
      for (int b = 0; b < s; ++b) Hss(a, b) = H_(sd[a], sd[b]);
    }
    const Eigen::VectorXd fs = Hss.llt().solve(rhs);
    for (int a = 0; a < s; ++a) f(sd[a]) = fs(a);
  }
  const Eigen::VectorXd x = lu_.solve(Eigen::VectorXd(f - fraw));
  RowMatrixX3d V = U0;
  for (int j = 0; j < nf_; ++j)
    for (int d = 0; d < 3; ++d) V(free_(j), d) += x(3 * j + d);
  return V;
}

}  // namespace bubble
