// Relaxed group lasso: the forces re-estimated on the group lasso's support without its L1
// term (the debiasing step of the force estimate).
//
// The group lasso finds which nodes carry force (its support) but takes a roughly fixed amount
// off every force it keeps. Given the support S, the refit keeps the data term and drops the
// penalty: the smallest correction dU (rim exactly zero) whose forces vanish off S,
//     minimise ||dU||^2  subject to  F_ext(U + dU, dp)_i = 0 for interior i not in S.
// With the rim eliminated, F_free = F_raw + K_ff x (x = dU on free dofs), so x = G (f - F_raw)
// with G = K_ff^{-1} and f the forces (zero off S). The minimum over f_S solves
//     H_SS f_S = (H F_raw)_S,   H = G^T G = (K_ff K_ff^T)^{-1},
// a dense 3|S| x 3|S| system: H is computed once per model (O(n^3) setup: LAPACK's Cholesky
// of the dense K_ff K_ff^T, then its inverse) for H_SS (O(|S|^3) per support,
// dense_cholesky.h). The right-hand side (H F_raw)_S comes from a sparse block LDL^T solve with
// K_ff K_ff^T (block_ldlt.h), not from H's columns: those are megabytes per support (6.5 MB for
// 134 nodes of the 749-node mesh) read at every modified-Newton step. The corrected
// displacement x = K_ff^{-1} (f - F_raw) = K_ff^T (K_ff K_ff^T)^{-1} (f - F_raw) takes a second
// solve with the same factor (no LU of K_ff: one factorization serves both).
// A firm press puts most of the membrane in the support (about 250 of 390 nodes at 10 N), and
// the dense |S|^3 then costs more than the sparse form. The same minimum is then taken over the
// constraints instead, C the free dofs off the support:
//     x = -K_C^T lambda,   (K_ff K_ff^T)_CC lambda = F_raw,C,
// a sparse symmetric positive definite system (K_ff K_ff^T couples nodes two rings apart),
// factored per frame by sparse Cholesky. Both forms give the same x to round-off; the refit
// takes the support form while the support is small, the constraint form once it is not.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <memory>
#include <vector>

#include "block_ldlt.h"
#include "dense_cholesky.h"
#include "membrane.h"

namespace bubble {

class SupportRefit {
 public:
  // K: 3N x 3N stiffness (need not be symmetric; K_ff must be invertible); area_normals: N x 3
  // (a_i n_i); boundary: rim node indices. Throws InputError on bad input or a singular K_ff.
  SupportRefit(const SparseMatrixd& K, const Eigen::Ref<const RowMatrixX3d>& area_normals,
               const Eigen::Ref<const Eigen::VectorXi>& boundary);

  // Corrected displacements V = U + dU (N x 3, rim rows exactly 0) for displacements U (N x 3,
  // m), pressure change dp (Pa) and the support (N bools; rim entries are ignored: the rim
  // always carries its reaction). Throws InputError on a wrong shape or non-finite input.
  RowMatrixX3d refit(const Eigen::Ref<const RowMatrixX3d>& U, double dp,
                     const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support) const;

  // One support's system, factored once for any number of refits on that support (the
  // nonlinear refit's modified-Newton steps keep the support): the dense support form or the
  // sparse constraint form, whichever is cheaper. Valid while its SupportRefit lives.
  class Factored {
   public:
    Factored(const SupportRefit& owner,
             const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support);
    // The correction x (3 nf) for raw forces fraw (3 nf).
    Eigen::VectorXd solve(const Eigen::VectorXd& fraw) const;

   private:
    const SupportRefit& owner_;
    std::vector<int> sd_, cd_;  // support and constrained dofs (free numbering)
    bool dense_ = true;
    DenseCholesky hss_;                        // H_SS (dense form)
    Eigen::SimplicialLLT<SparseMatrixd> mcc_;  // (K_ff K_ff^T)_CC (sparse form)
  };

  // refit() on a support factored once.
  RowMatrixX3d refit(const Eigen::Ref<const RowMatrixX3d>& U, double dp,
                     const Factored& system) const;

  // The correction x (N x 3, m, rim rows 0) that refit() adds to U0 = U + K_ff^{-1} q, for
  // nodal forces q (N x 3, N; rim rows ignored), without forming U0: its raw forces on the free
  // rows are F_raw(U) + q (K_ff K_ff^{-1} q = q), so no solve with K_ff is needed for them.
  RowMatrixX3d shifted_correction(const RowMatrixX3d& U, const RowMatrixX3d& q, double dp,
                                  const Factored& system) const;

  // The linear model's forces K W - dp a n (N x 3, N) for displacements W (N x 3, m).
  RowMatrixX3d linear_forces(const RowMatrixX3d& W, double dp) const;

  int n_nodes() const { return n_; }
  bool is_free(int node) const { return slot_(node) >= 0; }
  double setup_time_ms() const { return setup_ms_; }

 private:
  // U with the rim rows set to 0.
  RowMatrixX3d rim_zeroed(const RowMatrixX3d& U) const;
  // Raw forces at dU = 0 on the free dofs (3 nf): K U0 - dp a n.
  Eigen::VectorXd raw_forces(const RowMatrixX3d& U0, double dp) const;
  // The free nodes' rows of an N x 3 array as one 3 nf vector (free numbering).
  Eigen::VectorXd free_rows(const RowMatrixX3d& A) const;

  int n_ = 0, nf_ = 0;
  Eigen::VectorXi free_;  // free index -> node
  Eigen::VectorXi slot_;  // node -> free index, -1 on the rim
  SparseMatrixd K_;
  RowMatrixX3d an_;
  SparseMatrixd KffT_;                           // K_ff^T
  SparseMatrixd KKt_;                            // K_ff K_ff^T (sparse: two rings)
  std::shared_ptr<const BlockLDLT> kkt_factor_;  // of KKt_
  Eigen::MatrixXd H_;                            // (K_ff K_ff^T)^{-1}, 3 nf x 3 nf
  double setup_ms_ = 0;
};

}  // namespace bubble
