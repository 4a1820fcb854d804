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
  Result out;
  out.linear = refit_.refit(U, dp, system);  // rim rows exactly 0
  RowMatrixX3d W = out.linear;
  RowMatrixX3d F = green_.external_forces(W, dp);
  // Modified Newton on the linear K explodes far outside the membrane's range, line search
  // or not (8 -> 22 -> 978 N on a 20 mm dent, full steps): a step is kept while its residual
  // stays within kMaxGrowth of the linear refit's.
  constexpr double kMaxGrowth = 2.0;
  const double limit = kMaxGrowth * off_support_norm(F, support);
  for (int k = 0; k < iterations; ++k) {
    // the refit of U0 = U + K_ff^{-1} q, q = F_nl(W) - F_lin(W), is U0 + x: W_step = U + x
    const RowMatrixX3d W_step =
        clamped(U, refit_.shifted_correction(U, F - refit_.linear_forces(W, dp), dp, system));
    const Trial next = line_search(W, W_step, dp, support);
    if (!(next.residual <= limit)) break;  // diverging (or NaN): keep the last step within it
    W = next.W;
    F = next.F;
    ++out.steps;
  }
  out.nonlinear = W;
  return out;
}

NonlinearRefit::Trial NonlinearRefit::line_search(
    const RowMatrixX3d& W, const RowMatrixX3d& W_step, double dp,
    const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support) const {
  // The solve is the step's cost; a trial is one evaluation of the nonlinear forces.
  constexpr double kFractions[] = {1.0, 0.5, 0.25};
  Trial best;
  for (const double a : kFractions) {
    Trial t;
    t.W = W + a * (W_step - W);
    t.F = green_.external_forces(t.W, dp);
    t.residual = off_support_norm(t.F, support);
    if (t.residual < best.residual) best = std::move(t);  // NaN never; ties keep the longer step
  }
  return best;
}

double NonlinearRefit::off_support_norm(
    const RowMatrixX3d& F,
    const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support) const {
  double sum = 0.0;
  for (int i = 0; i < F.rows(); ++i)
    if (refit_.is_free(i) && !support(i)) sum += F.row(i).squaredNorm();
  return std::sqrt(sum);
}

RowMatrixX3d NonlinearRefit::clamped(const RowMatrixX3d& U, const RowMatrixX3d& x) const {
  RowMatrixX3d W = U + x;
  for (int i = 0; i < W.rows(); ++i)
    if (!refit_.is_free(i)) W.row(i).setZero();
  return W;
}

}  // namespace bubble
