#include "nonlinear_refit.h"

#include <cmath>
#include <string>

#include "errors.h"

namespace bubble {

NonlinearRefit::NonlinearRefit(const SupportRefit& refit, const GreenMembrane& green)
    : refit_(refit), green_(green) {
  require(refit.n_nodes() == green.n_nodes(),
          "the refit and the nonlinear membrane must have the same nodes");
}

NonlinearRefit::Result NonlinearRefit::refit(
    const Eigen::Ref<const RowMatrixX3d>& U_in, double dp,
    const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support, int iterations) const {
  const int n = n_nodes();
  require(U_in.rows() == n, "U must be N x 3 with N = " + std::to_string(n));
  require(support.size() == n, "support must have N = " + std::to_string(n) + " entries");
  require(U_in.allFinite(), "U must be finite");
  require(std::isfinite(dp), "dp must be finite");
  require(iterations >= 0, "iterations must be >= 0");
  const RowMatrixX3d U = U_in;
  const SupportRefit::Factored system(refit_, support);  // the support stays: factor once
  const RowMatrixX3d V = refit_.refit(U, dp, system);    // rim rows exactly 0
  RowMatrixX3d x = V - U;
  for (int k = 0; k < iterations; ++k) {
    const RowMatrixX3d W = clamped(U, x);
    const RowMatrixX3d q = green_.external_forces(W, dp) - refit_.linear_forces(W, dp);
    const RowMatrixX3d U0 = U + refit_.solve_free(q);
    x = refit_.refit(U0, dp, system) - U0;
  }
  return {V, clamped(U, x)};
}

RowMatrixX3d NonlinearRefit::clamped(const RowMatrixX3d& U, const RowMatrixX3d& x) const {
  RowMatrixX3d W = U + x;
  for (int i = 0; i < W.rows(); ++i)
    if (!refit_.is_free(i)) W.row(i).setZero();
  return W;
}

}  // namespace bubble
