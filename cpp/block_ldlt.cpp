#include "block_ldlt.h"

#include <Eigen/OrderingMethods>
#include <Eigen/SparseCholesky>
#include <algorithm>
#include <map>

#include "block_matrix.h"
#include "errors.h"

namespace bubble {

BlockLDLT::BlockLDLT(const Eigen::SparseMatrix<double>& M) {
  require(M.rows() == M.cols() && M.rows() % 3 == 0, "BlockLDLT: matrix must be 3n x 3n");
  nb_ = static_cast<int>(M.rows() / 3);
  // Node graph and its AMD ordering.
  std::vector<Eigen::Triplet<double>> tp;
  for (int col = 0; col < M.outerSize(); ++col)
    for (Eigen::SparseMatrix<double>::InnerIterator it(M, col); it; ++it)
      tp.emplace_back(static_cast<int>(it.row()) / 3, col / 3, 1.0);
  Eigen::SparseMatrix<double> G(nb_, nb_);
  G.setFromTriplets(tp.begin(), tp.end());
  Eigen::PermutationMatrix<Eigen::Dynamic, Eigen::Dynamic, int> P;
  Eigen::AMDOrdering<int> amd;
  amd(G, P);
  orig_.resize(nb_);
  std::vector<int> pos(nb_);
  for (int k = 0; k < nb_; ++k) {
    orig_[k] = P.indices()(k);
    pos[orig_[k]] = k;
  }
  // Permuted matrix (nodes reordered, components kept together).
  std::vector<Eigen::Triplet<double>> tm;
  tm.reserve(M.nonZeros());
  for (int col = 0; col < M.outerSize(); ++col)
    for (Eigen::SparseMatrix<double>::InnerIterator it(M, col); it; ++it) {
      const int r = static_cast<int>(it.row());
      tm.emplace_back(3 * pos[r / 3] + r % 3, 3 * pos[col / 3] + col % 3, it.value());
    }
  Eigen::SparseMatrix<double> Mp(M.rows(), M.cols());
  Mp.setFromTriplets(tm.begin(), tm.end());
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>, Eigen::Lower, Eigen::NaturalOrdering<int>>
      ldlt(Mp);
  require(ldlt.info() == Eigen::Success, "BlockLDLT: factorization failed");
  dinv_ = ldlt.vectorD().cwiseInverse();
  require(dinv_.allFinite(), "BlockLDLT: singular matrix");
  const auto& L = ldlt.matrixL().nestedExpression();
  ldiag_.assign(3 * static_cast<size_t>(nb_), 0.0);
  colptr_.assign(nb_ + 1, 0);
  rowblk_.clear();
  vals_.clear();
  std::map<int, int> slot;  // row block -> index within this column block
  for (int J = 0; J < nb_; ++J) {
    slot.clear();
    for (int c = 0; c < 3; ++c)
      for (Eigen::SparseMatrix<double>::InnerIterator it(L, 3 * J + c); it; ++it) {
        const int r = static_cast<int>(it.row());
        if (r <= 3 * J + c) continue;  // unit diagonal (stored or not)
        const int I = r / 3;
        if (I == J) {
          // Within the diagonal block: (1,0), (2,0), (2,1).
          const int k = (r % 3 == 1) ? 0 : (c == 0 ? 1 : 2);
          ldiag_[3 * J + k] = it.value();
          continue;
        }
        auto s = slot.find(I);
        if (s == slot.end()) s = slot.emplace(I, static_cast<int>(slot.size())).first;
        (void)s;
      }
    // Stable order of row blocks (ascending) for memory locality.
    std::vector<int> rows;
    rows.reserve(slot.size());
    for (auto& kv : slot) rows.push_back(kv.first);
    const size_t base = rowblk_.size();
    for (size_t i = 0; i < rows.size(); ++i) slot[rows[i]] = static_cast<int>(i);
    rowblk_.insert(rowblk_.end(), rows.begin(), rows.end());
    vals_.resize(9 * rowblk_.size(), 0.0);
    for (int c = 0; c < 3; ++c)
      for (Eigen::SparseMatrix<double>::InnerIterator it(L, 3 * J + c); it; ++it) {
        const int r = static_cast<int>(it.row());
        const int I = r / 3;
        if (I == J) continue;
        vals_[9 * (base + slot[I]) + block3::offset(r % 3, c)] = it.value();
      }
    colptr_[J + 1] = static_cast<int>(rowblk_.size());
  }
  w_.resize(M.rows());
  // Check the repacked solve against the matrix itself.
  Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(M.rows(), 1.0, 2.0), x(M.rows());
  solve(b, x);
  const double res = (M * x - b).norm() / b.norm();
  require(res < 1e-6, "BlockLDLT: block solve check failed (residual " + std::to_string(res) + ")");
}

void BlockLDLT::solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) const {
  double* w = w_.data();
  for (int k = 0; k < nb_; ++k) {
    const int o = orig_[k];
    w[3 * k] = b[3 * o];
    w[3 * k + 1] = b[3 * o + 1];
    w[3 * k + 2] = b[3 * o + 2];
  }
  // Forward: L y = w, column oriented: each solved node updates the rows below it.
  for (int J = 0; J < nb_; ++J) {
    double* y = w + 3 * J;
    const double* ld = &ldiag_[3 * J];
    y[1] -= ld[0] * y[0];
    y[2] -= ld[1] * y[0] + ld[2] * y[1];
    const Eigen::Vector3d yJ(y[0], y[1], y[2]);
    for (int p = colptr_[J]; p < colptr_[J + 1]; ++p) {
      const double* v = &vals_[9 * static_cast<size_t>(p)];
      double* t = w + 3 * rowblk_[p];
      Eigen::Map<Eigen::Vector2d>(t) -= block3::top(v) * yJ;
      t[2] -= block3::bottom(v).dot(yJ);
    }
  }
  for (int i = 0; i < 3 * nb_; ++i) w[i] *= dinv_[i];
  // Backward: L^T x = y. The products L_IJ^T x_I are summed elementwise over the column and
  // reduced once at its end.
  for (int J = nb_ - 1; J >= 0; --J) {
    Eigen::Matrix<double, 2, 3> top = Eigen::Matrix<double, 2, 3>::Zero();
    Eigen::RowVector3d bottom = Eigen::RowVector3d::Zero();
    for (int p = colptr_[J]; p < colptr_[J + 1]; ++p) {
      const double* v = &vals_[9 * static_cast<size_t>(p)];
      const double* t = w + 3 * rowblk_[p];
      top += block3::top(v).cwiseProduct(Eigen::Map<const Eigen::Vector2d>(t).replicate<1, 3>());
      bottom += t[2] * block3::bottom(v);
    }
    const Eigen::RowVector3d s = top.colwise().sum() + bottom;
    double* y = w + 3 * J;
    const double* ld = &ldiag_[3 * J];
    y[0] -= s[0];
    y[1] -= s[1];
    y[2] -= s[2];
    y[1] -= ld[2] * y[2];
    y[0] -= ld[0] * y[1] + ld[1] * y[2];
  }
  x.resize(3 * nb_);
  for (int k = 0; k < nb_; ++k) {
    const int o = orig_[k];
    x[3 * o] = w[3 * k];
    x[3 * o + 1] = w[3 * k + 1];
    x[3 * o + 2] = w[3 * k + 2];
  }
}

}  // namespace bubble
