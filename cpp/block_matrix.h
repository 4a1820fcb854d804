// Sparse matrix of dense 3 x 3 node blocks (block-compressed rows) for fast products.
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>
#include <vector>

namespace bubble {

class BlockMatrix3 {
 public:
  BlockMatrix3() = default;
  // A: (3 rows_b) x (3 cols_b) sparse matrix; every 3 x 3 block with an entry is stored dense.
  explicit BlockMatrix3(const Eigen::SparseMatrix<double>& A);
  // y = A x
  void multiply(const Eigen::VectorXd& x, Eigen::VectorXd& y) const;
  // y = A^T x
  void multiply_transposed(const Eigen::VectorXd& x, Eigen::VectorXd& y) const;
  // y += A^T x for an x that is zero outside the given block rows.
  void add_transposed_rows(const Eigen::VectorXd& x, const std::vector<int>& rows,
                           Eigen::VectorXd& y) const;

 private:
  void add_transposed_row(const Eigen::VectorXd& x, int i, Eigen::VectorXd& y) const;  // block row i
  int rows_ = 0, cols_ = 0;   // in blocks
  std::vector<int> rowptr_;   // rows_ + 1
  std::vector<int> colblk_;   // column block of each stored block
  std::vector<double> vals_;  // 9 per block, row-major
};

}  // namespace bubble
