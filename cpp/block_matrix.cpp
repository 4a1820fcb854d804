#include "block_matrix.h"

#include <array>
#include <map>

#include "errors.h"

namespace bubble {

BlockMatrix3::BlockMatrix3(const Eigen::SparseMatrix<double>& A) {
  require(A.rows() % 3 == 0 && A.cols() % 3 == 0, "BlockMatrix3: dimensions must be 3n");
  rows_ = static_cast<int>(A.rows() / 3);
  cols_ = static_cast<int>(A.cols() / 3);
  std::vector<std::map<int, std::array<double, 9>>> rows(rows_);
  for (int col = 0; col < A.outerSize(); ++col)
    for (Eigen::SparseMatrix<double>::InnerIterator it(A, col); it; ++it) {
      const int r = static_cast<int>(it.row());
      auto& blk = rows[r / 3][col / 3];
      if (blk.empty()) blk.fill(0.0);
      blk[3 * (r % 3) + col % 3] = it.value();
    }
  rowptr_.assign(rows_ + 1, 0);
  for (int i = 0; i < rows_; ++i) {
    for (auto& kv : rows[i]) {
      colblk_.push_back(kv.first);
      vals_.insert(vals_.end(), kv.second.begin(), kv.second.end());
    }
    rowptr_[i + 1] = static_cast<int>(colblk_.size());
  }
}

void BlockMatrix3::multiply(const Eigen::VectorXd& x, Eigen::VectorXd& y) const {
  y.resize(3 * rows_);
  const double* xp = x.data();
  for (int i = 0; i < rows_; ++i) {
    double s0 = 0, s1 = 0, s2 = 0;
    for (int p = rowptr_[i]; p < rowptr_[i + 1]; ++p) {
      const double* v = &vals_[9 * static_cast<size_t>(p)];
      const double* t = xp + 3 * colblk_[p];
      s0 += v[0] * t[0] + v[1] * t[1] + v[2] * t[2];
      s1 += v[3] * t[0] + v[4] * t[1] + v[5] * t[2];
      s2 += v[6] * t[0] + v[7] * t[1] + v[8] * t[2];
    }
    y[3 * i] = s0;
    y[3 * i + 1] = s1;
    y[3 * i + 2] = s2;
  }
}

void BlockMatrix3::multiply_transposed(const Eigen::VectorXd& x, Eigen::VectorXd& y) const {
  y.setZero(3 * cols_);
  for (int i = 0; i < rows_; ++i) add_transposed_row(x, i, y);
}

void BlockMatrix3::add_transposed_rows(const Eigen::VectorXd& x, const std::vector<int>& rows,
                                       Eigen::VectorXd& y) const {
  for (const int i : rows) add_transposed_row(x, i, y);
}

void BlockMatrix3::add_transposed_row(const Eigen::VectorXd& x, int i, Eigen::VectorXd& y) const {
  double* yp = y.data();
  const double x0 = x[3 * i], x1 = x[3 * i + 1], x2 = x[3 * i + 2];
  for (int p = rowptr_[i]; p < rowptr_[i + 1]; ++p) {
    const double* v = &vals_[9 * static_cast<size_t>(p)];
    double* t = yp + 3 * colblk_[p];
    t[0] += v[0] * x0 + v[3] * x1 + v[6] * x2;
    t[1] += v[1] * x0 + v[4] * x1 + v[7] * x2;
    t[2] += v[2] * x0 + v[5] * x1 + v[8] * x2;
  }
}

}  // namespace bubble
