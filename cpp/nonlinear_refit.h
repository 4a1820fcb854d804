// The support refit with the nonlinear membrane's forces (GreenMembrane): the smallest
// correction x of U whose nonlinear forces vanish off the support, by modified Newton steps on
// the linear stiffness K from the linear refit's V = U + x0.
//
// Each step is the linear refit of a shifted U0 = U + K_ff^{-1} q, q = F_nl(W) - F_lin(W) at
// W = U + x (rim rows 0): the linear refit's raw forces are then F_nl(W) - K x, so its
// constraint is the linearisation of F_nl about W and its correction is still measured from U.
// Each step is taken as the fraction (1, 1/2 or 1/4) of it that leaves the least residual (the
// nonlinear forces off the support): where a firm press stretches the membrane its tangent
// stiffness exceeds twice K in some modes and the full step overshoots (the residual
// oscillates, then diverges: 3.0 -> 3.7 -> 6.4 -> 29 N on a 10 N line press on 749 nodes),
// where half steps converge (3.0 -> 1.6 -> 0.5 -> 0.24 N); on a light press the full step is
// the best, and converges fastest.
#pragma once

#include <Eigen/Core>
#include <limits>

#include "green_membrane.h"
#include "membrane.h"
#include "support_refit.h"

namespace bubble {

class NonlinearRefit {
 public:
  // Holds references: refit and green must outlive this object and have the same node count
  // (InputError otherwise).
  NonlinearRefit(const SupportRefit& refit, const GreenMembrane& green);

  // The linear refit's V and the nonlinear one's W (both N x 3, m, rim rows exactly 0): W after
  // up to `iterations` modified Newton steps from V (each with its line search), for
  // displacements U (N x 3), pressure change dp (Pa) and the support (N bools), the support's
  // system factored once for all of them. A step is kept while the nonlinear forces off the support
  // (the constraint's residual) stay within twice the linear refit's: far outside the membrane's
  // range (centimetres of tracking noise, a dent deeper than the bubble) the iteration diverges,
  // and W stops at the last step within that bound; `steps` counts the kept ones (0: W = V, whose
  // nonlinear forces are not to be trusted). Throws InputError on a wrong shape, non-finite input
  // or iterations < 0.
  struct Result {
    RowMatrixX3d linear, nonlinear;
    int steps = 0;
  };
  Result refit(const Eigen::Ref<const RowMatrixX3d>& U, double dp,
               const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support,
               int iterations) const;

  int n_nodes() const { return refit_.n_nodes(); }

 private:
  struct Trial {
    RowMatrixX3d W, F;
    double residual = std::numeric_limits<double>::infinity();
  };
  // The point W + a (W_step - W), a in {1, 1/2, 1/4}, with the least residual, its forces and
  // residual (residual infinite when no trial is finite).
  Trial line_search(const RowMatrixX3d& W, const RowMatrixX3d& W_step, double dp,
                    const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support) const;
  // U + x with the rim rows set to exactly 0.
  RowMatrixX3d clamped(const RowMatrixX3d& U, const RowMatrixX3d& x) const;
  // The norm of the forces F on the free nodes off the support.
  double off_support_norm(
      const RowMatrixX3d& F,
      const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support) const;

  const SupportRefit& refit_;
  const GreenMembrane& green_;
};

}  // namespace bubble
