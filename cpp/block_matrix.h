// Sparse matrix of dense 3 x 3 node blocks (block-compressed rows) for fast products.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <vector>

namespace bubble {

// How a dense 3 x 3 block is stored (here and in BlockLDLT): rows 0-1 column-major, then
// row 2, so that products work on pairs of rows with packed arithmetic (SSE2).
namespace block3 {
using Top = Eigen::Map<const Eigen::Matrix<double, 2, 3>>;  // rows 0-1 of the block at v
using Bottom = Eigen::Map<const Eigen::RowVector3d>;        // row 2 of the block at v
inline Top top(const double* v) { return Top(v); }
inline Bottom bottom(const double* v) { return Bottom(v + 6); }
inline int offset(int row, int col) { return row < 2 ? 2 * col + row : 6 + col; }
}  // namespace block3

class BlockMatrix3 {
 public:
  BlockMatrix3() = default;
  // A: (3 rows_b) x (3 cols_b) sparse matrix; every 3 x 3 block with an entry is stored dense.
  explicit BlockMatrix3(const Eigen::SparseMatrix<double>& A);
  // y = A x
  void multiply(const Eigen::VectorXd& x, Eigen::VectorXd& y) const;

 private:
  int rows_ = 0, cols_ = 0;   // in blocks
  std::vector<int> rowptr_;   // rows_ + 1
  std::vector<int> colblk_;   // column block of each stored block
  std::vector<double> vals_;  // 9 per block, layout of block3
};

}  // namespace bubble
