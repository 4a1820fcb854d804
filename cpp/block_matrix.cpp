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
      blk[block3::offset(r % 3, col % 3)] = it.value();
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
  for (int i = 0; i < rows_; ++i) {
    Eigen::Vector2d top = Eigen::Vector2d::Zero();
    double bottom = 0;
    for (int p = rowptr_[i]; p < rowptr_[i + 1]; ++p) {
      const double* v = &vals_[9 * static_cast<size_t>(p)];
      const Eigen::Vector3d xj = x.segment<3>(3 * colblk_[p]);
      top.noalias() += block3::top(v) * xj;
      bottom += block3::bottom(v).dot(xj);
    }
    y.segment<2>(3 * i) = top;
    y[3 * i + 2] = bottom;
  }
}

}  // namespace bubble
