#include "block_ldlt.h"

#include <Eigen/OrderingMethods>
#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <string>

#include "block_matrix.h"
#include "errors.h"

namespace bubble {

using SparseMatrix = Eigen::SparseMatrix<double>;
using Block = Eigen::Matrix3d;

// What depends only on the pattern of M.
struct BlockLDLT::Structure {
  int nb = 0;
  std::vector<int> outer, inner;  // the pattern of M it was built for (CSC, compressed)
  std::vector<int> orig;          // permuted node k -> original node
  // L's strictly lower blocks by block columns (rows ascending), and the same by block rows
  // (columns ascending): position in the columns' storage, and that position's column.
  std::vector<int> colptr, rowblk;
  std::vector<int> rowptr, rowpos, poscol;
  // M's blocks on and below the diagonal, by permuted block columns: row block, and for each
  // of the 9 entries (block3 layout) the index of its value in M (-1: not stored).
  std::vector<int> mcolptr, mrowblk, mvalue;

  bool matches(const SparseMatrix& M) const {
    return M.rows() == 3 * nb && M.isCompressed() &&
           std::equal(outer.begin(), outer.end(), M.outerIndexPtr()) &&
           static_cast<long>(inner.size()) == M.nonZeros() &&
           std::equal(inner.begin(), inner.end(), M.innerIndexPtr());
  }
};

namespace {
// AMD on the node graph: the three dofs of a node stay together, so L has 3 x 3 blocks.
std::vector<int> node_ordering(const SparseMatrix& M, int nb) {
  std::vector<Eigen::Triplet<double>> tp;
  for (int col = 0; col < M.outerSize(); ++col)
    for (SparseMatrix::InnerIterator it(M, col); it; ++it)
      tp.emplace_back(static_cast<int>(it.row()) / 3, col / 3, 1.0);
  SparseMatrix G(nb, nb);
  G.setFromTriplets(tp.begin(), tp.end());
  Eigen::PermutationMatrix<Eigen::Dynamic, Eigen::Dynamic, int> P;
  Eigen::AMDOrdering<int>()(G, P);
  return std::vector<int>(P.indices().data(), P.indices().data() + nb);
}

// Where M's values go: its blocks on and below the diagonal in the permuted order. A stored
// entry above the diagonal fills its mirror image, so M may hold either triangle or both.
void gather_map(const SparseMatrix& M, const std::vector<int>& pos, BlockLDLT::Structure& s) {
  std::vector<std::map<int, std::array<int, 9>>> cols(s.nb);
  for (int c = 0; c < M.outerSize(); ++c)
    for (SparseMatrix::InnerIterator it(M, c); it; ++it) {
      const int r = static_cast<int>(it.row());
      int I = pos[r / 3], J = pos[c / 3], ri = r % 3, ci = c % 3;
      if (I < J) std::swap(I, J), std::swap(ri, ci);
      auto [slot, fresh] = cols[J].try_emplace(I);
      if (fresh) slot->second.fill(-1);
      slot->second[block3::offset(ri, ci)] = static_cast<int>(&it.value() - M.valuePtr());
      if (I == J) slot->second[block3::offset(ci, ri)] = slot->second[block3::offset(ri, ci)];
    }
  s.mcolptr.assign(s.nb + 1, 0);
  for (int J = 0; J < s.nb; ++J) {
    for (const auto& [I, idx] : cols[J]) {
      s.mrowblk.push_back(I);
      s.mvalue.insert(s.mvalue.end(), idx.begin(), idx.end());
    }
    s.mcolptr[J + 1] = static_cast<int>(s.mrowblk.size());
  }
}

// The block pattern of L: column J holds M's rows below J and its children's rows below J,
// the parent of J being its first row (the elimination tree of the node graph).
void symbolic(BlockLDLT::Structure& s) {
  std::vector<std::vector<int>> children(s.nb);
  std::vector<int> mark(s.nb, -1), rows;
  s.colptr.assign(s.nb + 1, 0);
  for (int J = 0; J < s.nb; ++J) {
    rows.clear();
    auto add = [&](int I) {
      if (I > J && mark[I] != J) mark[I] = J, rows.push_back(I);
    };
    for (int q = s.mcolptr[J]; q < s.mcolptr[J + 1]; ++q) add(s.mrowblk[q]);
    for (const int C : children[J])
      for (int p = s.colptr[C]; p < s.colptr[C + 1]; ++p) add(s.rowblk[p]);
    std::sort(rows.begin(), rows.end());
    if (!rows.empty()) children[rows.front()].push_back(J);
    s.rowblk.insert(s.rowblk.end(), rows.begin(), rows.end());
    s.colptr[J + 1] = static_cast<int>(s.rowblk.size());
  }
  // The same pattern by rows, for the left-looking updates.
  s.rowptr.assign(s.nb + 1, 0);
  for (const int I : s.rowblk) ++s.rowptr[I + 1];
  for (int I = 0; I < s.nb; ++I) s.rowptr[I + 1] += s.rowptr[I];
  s.rowpos.resize(s.rowblk.size());
  s.poscol.resize(s.rowblk.size());
  std::vector<int> next(s.rowptr.begin(), s.rowptr.end() - 1);
  for (int K = 0; K < s.nb; ++K)
    for (int p = s.colptr[K]; p < s.colptr[K + 1]; ++p) {
      s.rowpos[next[s.rowblk[p]]++] = p;
      s.poscol[p] = K;
    }
}

Block load(const double* v) {
  Block b;
  b.topRows<2>() = block3::top(v);
  b.row(2) = block3::bottom(v);
  return b;
}

void store(const Block& b, double* v) {
  for (int c = 0; c < 3; ++c)
    for (int r = 0; r < 3; ++r) v[block3::offset(r, c)] = b(r, c);
}
}  // namespace

BlockLDLT::BlockLDLT(const SparseMatrix& M) : BlockLDLT(M, nullptr) {}

BlockLDLT::BlockLDLT(const SparseMatrix& M, std::shared_ptr<Structure> structure) {
  require(M.rows() == M.cols() && M.rows() % 3 == 0, "BlockLDLT: matrix must be 3n x 3n");
  require(M.isCompressed(), "BlockLDLT: matrix must be compressed");
  if (structure && structure->matches(M)) {
    structure_ = std::move(structure);
    factorize(M);
    return;
  }
  auto s = std::make_shared<Structure>();
  s->nb = static_cast<int>(M.rows() / 3);
  s->outer.assign(M.outerIndexPtr(), M.outerIndexPtr() + M.outerSize() + 1);
  s->inner.assign(M.innerIndexPtr(), M.innerIndexPtr() + M.nonZeros());
  s->orig = node_ordering(M, s->nb);
  std::vector<int> pos(s->nb);
  for (int k = 0; k < s->nb; ++k) pos[s->orig[k]] = k;
  gather_map(M, pos, *s);
  symbolic(*s);
  structure_ = s;
  factorize(M);
}

// Left-looking: column J of the Schur complement, S_IJ = M_IJ - sum_K L_IK D_K L_JK^T over the
// columns K with a block in row J, then S_JJ = L_JJ D_J L_JJ^T and L_IJ = S_IJ (D_J L_JJ^T)^-1.
void BlockLDLT::factorize(const SparseMatrix& M) {
  const Structure& s = *structure_;
  const int nb = s.nb;
  ldiag_.assign(3 * static_cast<size_t>(nb), 0.0);
  vals_.assign(9 * s.rowblk.size(), 0.0);
  dinv_.resize(3 * nb);
  std::vector<Block> W(nb, Block::Zero());  // column J's Schur blocks, by row block
  const double* mv = M.valuePtr();
  for (int J = 0; J < nb; ++J) {
    for (int q = s.mcolptr[J]; q < s.mcolptr[J + 1]; ++q) {
      const int* idx = &s.mvalue[9 * static_cast<size_t>(q)];
      double v[9];
      for (int k = 0; k < 9; ++k) v[k] = idx[k] >= 0 ? mv[idx[k]] : 0.0;
      W[s.mrowblk[q]] += load(v);
    }
    for (int r = s.rowptr[J]; r < s.rowptr[J + 1]; ++r) {
      const int p = s.rowpos[r], K = s.poscol[p];
      const Block T = (load(&vals_[9 * static_cast<size_t>(p)]) *
                       Eigen::Vector3d(1 / dinv_[3 * K], 1 / dinv_[3 * K + 1], 1 / dinv_[3 * K + 2])
                           .asDiagonal())
                          .transpose();  // D_K L_JK^T
      for (int q = p; q < s.colptr[K + 1]; ++q)
        W[s.rowblk[q]].noalias() -= load(&vals_[9 * static_cast<size_t>(q)]) * T;
    }
    const Block& S = W[J];
    const double d0 = S(0, 0), l10 = S(1, 0) / d0, l20 = S(2, 0) / d0;
    const double d1 = S(1, 1) - l10 * l10 * d0, l21 = (S(2, 1) - l20 * l10 * d0) / d1;
    const double d2 = S(2, 2) - l20 * l20 * d0 - l21 * l21 * d1;
    require(d0 > 0 && d1 > 0 && d2 > 0 && std::isfinite(d0 + d1 + d2),
            "BlockLDLT: matrix is not positive definite");
    ldiag_[3 * J] = l10, ldiag_[3 * J + 1] = l20, ldiag_[3 * J + 2] = l21;
    dinv_.segment<3>(3 * J) = Eigen::Vector3d(1 / d0, 1 / d1, 1 / d2);
    for (int p = s.colptr[J]; p < s.colptr[J + 1]; ++p) {
      Block& X = W[s.rowblk[p]];  // rows of S_IJ -> rows of L_IJ: solve x (D_J L_JJ^T) = s
      X.col(1) -= l10 * X.col(0);
      X.col(2) -= l20 * X.col(0) + l21 * X.col(1);
      X *= dinv_.segment<3>(3 * J).asDiagonal();
      store(X, &vals_[9 * static_cast<size_t>(p)]);
      X.setZero();
    }
    W[J].setZero();
  }
  w_.resize(M.rows());
  // Check the block solve against the matrix itself.
  Eigen::VectorXd b = Eigen::VectorXd::LinSpaced(M.rows(), 1.0, 2.0), x(M.rows());
  solve(b, x);
  const double res = (M * x - b).norm() / b.norm();
  require(res < 1e-6, "BlockLDLT: block solve check failed (residual " + std::to_string(res) + ")");
}

long BlockLDLT::block_count() const { return static_cast<long>(structure_->rowblk.size()); }

double BlockLDLT::memory_bytes() const {
  return static_cast<double>(sizeof(double)) *
         static_cast<double>(vals_.size() + ldiag_.size() + dinv_.size() + w_.size());
}

void BlockLDLT::solve(const Eigen::VectorXd& b, Eigen::VectorXd& x, Eigen::VectorXd& work) const {
  const Structure& s = *structure_;
  const int nb = s.nb;
  work.resize(3 * nb);
  // Raw pointers: the stores into w could alias the vectors' own members, which would make
  // the compiler reload them for every block.
  double* w = work.data();
  const double* vals = vals_.data();
  const int* colptr = s.colptr.data();
  const int* rowblk = s.rowblk.data();
  for (int k = 0; k < nb; ++k) {
    const int o = s.orig[k];
    w[3 * k] = b[3 * o];
    w[3 * k + 1] = b[3 * o + 1];
    w[3 * k + 2] = b[3 * o + 2];
  }
  // Forward: L y = w, column oriented: each solved node updates the rows below it.
  for (int J = 0; J < nb; ++J) {
    double* y = w + 3 * J;
    const double* ld = &ldiag_[3 * J];
    y[1] -= ld[0] * y[0];
    y[2] -= ld[1] * y[0] + ld[2] * y[1];
    const Eigen::Vector3d yJ(y[0], y[1], y[2]);
    for (int p = colptr[J], end = colptr[J + 1]; p < end; ++p) {
      const double* v = vals + 9 * static_cast<size_t>(p);
      double* t = w + 3 * rowblk[p];
      Eigen::Map<Eigen::Vector2d>(t) -= block3::top(v) * yJ;
      t[2] -= block3::bottom(v).dot(yJ);
    }
  }
  for (int i = 0; i < 3 * nb; ++i) w[i] *= dinv_[i];
  // Backward: L^T x = y. The products L_IJ^T x_I are summed elementwise over the column and
  // reduced once at its end.
  for (int J = nb - 1; J >= 0; --J) {
    Eigen::Matrix<double, 2, 3> top = Eigen::Matrix<double, 2, 3>::Zero();
    Eigen::RowVector3d bottom = Eigen::RowVector3d::Zero();
    for (int p = colptr[J], end = colptr[J + 1]; p < end; ++p) {
      const double* v = vals + 9 * static_cast<size_t>(p);
      const double* t = w + 3 * rowblk[p];
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
  x.resize(3 * nb);
  for (int k = 0; k < nb; ++k) {
    const int o = s.orig[k];
    x[3 * o] = w[3 * k];
    x[3 * o + 1] = w[3 * k + 1];
    x[3 * o + 2] = w[3 * k + 2];
  }
}

}  // namespace bubble
