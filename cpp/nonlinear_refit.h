// The support refit with the nonlinear membrane's forces (GreenMembrane): the smallest
// correction x of U whose nonlinear forces vanish off the support, by modified Newton steps on
// the linear stiffness K from the linear refit's V = U + x0.
//
// Each step is the linear refit of a shifted U0 = U + K_ff^{-1} q, q = F_nl(W) - F_lin(W) at
// W = U + x (rim rows 0): the linear refit's raw forces are then F_nl(W) - K x, so its
// constraint is the linearisation of F_nl about W and its correction is still measured from U.
#pragma once

#include <Eigen/Core>

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
  // `iterations` modified Newton steps from V, for displacements U (N x 3), pressure change dp
  // (Pa) and the support (N bools), the support's system factored once for all of them.
  // Throws InputError on a wrong shape, non-finite input or iterations < 0.
  struct Result {
    RowMatrixX3d linear, nonlinear;
  };
  Result refit(const Eigen::Ref<const RowMatrixX3d>& U, double dp,
               const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support,
               int iterations) const;

  int n_nodes() const { return refit_.n_nodes(); }

 private:
  // U + x with the rim rows set to exactly 0.
  RowMatrixX3d clamped(const RowMatrixX3d& U, const RowMatrixX3d& x) const;

  const SupportRefit& refit_;
  const GreenMembrane& green_;
};

}  // namespace bubble
