// Sparse LDL^T factorization with 3 x 3 node blocks, for the ADMM x-update.
//
// The system matrix couples the three displacement components of every node, so after a
// fill-reducing ordering of the *nodes* (AMD on the node graph) the factor L is made of dense
// 3 x 3 blocks. Eigen's SimplicialLDLT computes the numbers; they are then repacked into
// block-compressed columns, which makes the triangular solves (the per-iteration cost of
// ADMM) several times faster than scalar CSC solves. The block solve is checked against the
// matrix once after factorizing.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <vector>

namespace bubble {

class BlockLDLT {
 public:
  // M: symmetric positive definite, size 3n x 3n, dofs grouped per node. Throws InputError
  // if the factorization fails.
  explicit BlockLDLT(const Eigen::SparseMatrix<double>& M);
  // x = M^{-1} b. x and b may not alias.
  void solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) const;
  long block_count() const { return static_cast<long>(rowblk_.size()); }

 private:
  int nb_ = 0;
  std::vector<int> orig_;      // permuted node k -> original node
  Eigen::VectorXd dinv_;       // 3 nb, permuted order
  std::vector<double> ldiag_;  // per block column: l10, l20, l21 of its unit-lower diagonal
  std::vector<int> colptr_;    // nb + 1
  std::vector<int> rowblk_;    // row block of each stored block
  std::vector<double> vals_;   // 9 per stored block: rows 0-1 column-major, then row 2
  mutable Eigen::VectorXd w_;
};

}  // namespace bubble
