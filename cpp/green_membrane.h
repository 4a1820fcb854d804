// The inflated membrane with its geometric nonlinearity: Green-Lagrange strain, second
// Piola-Kirchhoff tension T0 I + C : E, pressure on the displaced surface (docs/method.md,
// "Geometric nonlinearity (the refit's forces)"). The reference definition is the NumPy
// bubble_rt.estimation.membrane.GreenMembrane; this is the same model, to round-off.
#pragma once

#include <Eigen/Core>
#include <vector>

#include "membrane.h"

namespace bubble {

class GreenMembrane {
 public:
  // Reference vertices (N x 3, m), triangles (T x 3), material (E Pa, nu, thickness m), rest
  // tension T0 (N/m) and rest gauge pressure p0 (Pa). Throws InputError on bad shapes,
  // out-of-range indices, degenerate triangles or non-finite parameters.
  GreenMembrane(const Eigen::Ref<const RowMatrixX3d>& vertices,
                const Eigen::Ref<const RowMatrixX3i>& triangles, double E, double nu,
                double thickness, double tension, double p0);

  // F_ext(U, dp) = [f_int(X + U) - f_int(X)] - [f_p(X + U, p0 + dp) - f_p(X, p0)] (N x 3, N)
  // for displacements U (N x 3, m) and pressure change dp (Pa). Throws InputError on a wrong
  // shape or non-finite input.
  RowMatrixX3d external_forces(const Eigen::Ref<const RowMatrixX3d>& U, double dp) const;

  int n_nodes() const { return static_cast<int>(X_.rows()); }

 private:
  using Grad = Eigen::Matrix<double, 2, 3>;  // rows: d/dxi_1, d/dxi_2; columns: corners

  // Nodal internal forces sum_t A F S g_a at positions x (N x 3).
  RowMatrixX3d internal(const RowMatrixX3d& x) const;
  // Nodal forces p (x1 - x0) x (x2 - x0) / 6 of a pressure p at positions x (N x 3).
  RowMatrixX3d pressure(const RowMatrixX3d& x, double p) const;

  RowMatrixX3d X_;
  RowMatrixX3i T_;
  std::vector<Grad> G_;   // in-plane shape-function gradients per triangle (1/m)
  std::vector<Grad> AG_;  // the same times the reference area
  double c_ = 0, nu_ = 0, tension_ = 0, p0_ = 0;
  RowMatrixX3d f0_;  // f_int(X) - f_p(X, p0)
};

}  // namespace bubble
