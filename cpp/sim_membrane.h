// Nonlinear membrane system for the simulator: incompressible neo-Hookean constant-strain
// triangles, enclosed-volume terms and a sparse LDL^T solver on a fixed sparsity pattern.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <vector>

namespace bubble {

using SimRowMatrixX3d = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
using SimRowMatrixX3i = Eigen::Matrix<int, Eigen::Dynamic, 3, Eigen::RowMajor>;
using SimRowMatrixX9d = Eigen::Matrix<double, Eigen::Dynamic, 9, Eigen::RowMajor>;
// Read-only views: numpy arrays (C-contiguous float64) bind to these without a copy.
using SimRef3 = Eigen::Ref<const SimRowMatrixX3d>;
using SimRef9 = Eigen::Ref<const SimRowMatrixX9d>;

// Strain energy per unit rest area W = mu_t / 2 (|a|^2 + |b|^2 + 1 / |a x b|^2 - 3), with
// (a, b) the deformed images of an orthonormal rest frame of each triangle. Nodes listed in
// `fixed` carry no degrees of freedom (the clamped rim). Element Hessians are projected to
// positive semi-definite in the 6-dimensional deformation-gradient space.
class SimMembrane {
 public:
  SimMembrane(const SimRowMatrixX3d& rest, const SimRowMatrixX3i& triangles,
              const Eigen::VectorXi& fixed, double mu_t);

  int n_nodes() const { return n_nodes_; }
  int n_free_dofs() const { return n_free_; }
  long nnz() const { return static_cast<long>(H_.nonZeros()); }

  // Elastic energy (J); +inf if a triangle collapses. Gradient (N) into `grad` when non-null.
  double energy(const SimRef3& x, SimRowMatrixX3d* grad) const;
  // Enclosed volume (m^3) between the surface and the plane through the origin the rim lies
  // in; gradient (m^2) into `grad` when non-null.
  double volume(const SimRef3& x, SimRowMatrixX3d* grad) const;
  // Assemble H = elastic + volume_scale * d2V/dx2 + per-node 3x3 blocks (row-major, N x 9)
  // + shift * I on the free dofs, and factorise it. With `project` each element's elastic
  // Hessian is clamped to positive semi-definite. False if the factorisation fails.
  bool factorize(const SimRef3& x, double volume_scale, const SimRef9& blocks, double shift,
                 bool project);
  // The assembly step of `factorize` alone (H is kept for `multiply`).
  void assemble(const SimRef3& x, double volume_scale, const SimRef9& blocks, double shift,
                bool project);
  // Factorise the last assembled H (the symbolic analysis is done once). False on failure.
  bool factorize_assembled();
  // H v with the last assembled H (rows of fixed nodes zero).
  SimRowMatrixX3d multiply(const SimRef3& v) const;
  // Nonzeros of the last factor L.
  long factor_nnz() const;
  // Non-positive pivots of the last LDL^T factorisation (0: H positive definite).
  int nonpositive_pivots() const;
  // Solve H y = rhs with the last factorisation; rows of fixed nodes are returned as zero.
  SimRowMatrixX3d solve(const SimRef3& rhs) const;

 private:
  int n_nodes_ = 0;
  int n_free_ = 0;
  double mu_t_ = 0.0;
  SimRowMatrixX3i tri_;
  Eigen::VectorXd area0_;                          // rest areas
  Eigen::Matrix<double, Eigen::Dynamic, 6> coef_;  // per triangle: g0a g0b g1a g1b g2a g2b
  std::vector<int> dof_;                           // node -> first free dof, or -1
  std::vector<int> elem_slot_;     // per triangle 81 value indices (lower part) or -1
  std::vector<int> node_slot_;     // per node 9 value indices (lower part) or -1
  std::vector<int> diag_slot_;     // per free dof
  Eigen::SparseMatrix<double> H_;  // lower triangle, column-major
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>, Eigen::Lower> ldlt_;
  bool analyzed_ = false;
  bool assembled_ = false;
  bool factorized_ = false;
};

}  // namespace bubble
