// Sparse LDL^T factorization with 3 x 3 node blocks, for the ADMM x-update.
//
// The system matrix couples the three displacement components of every node, so after a
// fill-reducing ordering of the *nodes* (AMD on the node graph) the factor L is made of dense
// 3 x 3 blocks: M = L D L^T with unit lower triangular 3 x 3 diagonal blocks and D diagonal
// (the scalar LDL^T's factor, grouped by node). Both the factorization (left-looking, one 3 x 3
// block product per update) and the triangular solves (the per-iteration cost of ADMM) work on
// the blocks, several times faster than on scalars. The blocks are stored so that the solves
// use packed arithmetic (block_matrix.h, block3). The block solve is checked against the
// matrix once after factorizing.
//
// The ordering, the symbolic factorization (the block pattern of L, from the elimination tree
// of the node graph) and where M's numbers go depend only on the sparsity pattern; they are
// computed once (Structure) and shared by every factorization of a matrix with the same pattern
// (the solver refactors P + sigma I + rho A^T A as rho moves).
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <memory>
#include <vector>

namespace bubble {

class BlockLDLT {
 public:
  struct Structure;
  // M: symmetric positive definite, size 3n x 3n, dofs grouped per node. Throws InputError
  // if the factorization fails.
  explicit BlockLDLT(const Eigen::SparseMatrix<double>& M);
  // The same with the pattern analysis of an earlier factorization, reused when M has the
  // same sparsity pattern (otherwise analysed afresh).
  BlockLDLT(const Eigen::SparseMatrix<double>& M, std::shared_ptr<Structure> structure);
  // x = M^{-1} b. x and b may not alias. Uses the factorization's own workspace: one caller at a
  // time (the ADMM's per-iteration solves, which should not allocate).
  void solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) const { solve(b, x, w_); }
  // The same in the caller's workspace (resized to 3n): safe from several threads at once.
  void solve(const Eigen::VectorXd& b, Eigen::VectorXd& x, Eigen::VectorXd& work) const;
  long block_count() const;
  // Bytes held by this factorization's numbers (the shared structure not counted).
  double memory_bytes() const;
  const std::shared_ptr<Structure>& structure() const { return structure_; }

 private:
  void factorize(const Eigen::SparseMatrix<double>& M);

  std::shared_ptr<Structure> structure_;
  Eigen::VectorXd dinv_;       // 3 nb, permuted order
  std::vector<double> ldiag_;  // per block column: l10, l20, l21 of its unit-lower diagonal
  std::vector<double> vals_;   // 9 per stored block (layout of block3), by block columns
  mutable Eigen::VectorXd w_;
};

}  // namespace bubble
