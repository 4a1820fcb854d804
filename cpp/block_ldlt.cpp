#include "block_ldlt.h"

#include <Eigen/OrderingMethods>
#include <algorithm>
#include <limits>
#include <map>
#include <string>

#include "block_matrix.h"
#include "errors.h"

namespace bubble {

using SparseMatrix = Eigen::SparseMatrix<double>;

// What depends only on the pattern of M.
struct BlockLDLT::Structure {
  int nb = 0;
  std::vector<int> outer, inner;  // the pattern of M it was built for (CSC, compressed)
  std::vector<int> orig;          // permuted node k -> original node
  std::vector<int> mp_from_m;     // value q of the permuted matrix = value mp_from_m[q] of M
  SparseMatrix Mp;                // the permuted matrix (values overwritten per factorization)
  Eigen::SimplicialLDLT<SparseMatrix, Eigen::Lower, Eigen::NaturalOrdering<int>> ldlt;
  // Value p of L goes to vals_[to_vals[p]] (>= 0), to ldiag_[-1 - to_vals[p]], or nowhere
  // (kSkip: the unit diagonal).
  static constexpr long kSkip = std::numeric_limits<long>::min();
  std::vector<long> to_vals;
  std::vector<int> colptr;  // nb + 1
  std::vector<int> rowblk;  // row block of each stored block

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

// The permuted pattern (nodes reordered, components kept together); its values are the
// indices of M's values, so that later factorizations only copy numbers.
void permute_pattern(const SparseMatrix& M, BlockLDLT::Structure& s) {
  std::vector<int> pos(s.nb);
  for (int k = 0; k < s.nb; ++k) pos[s.orig[k]] = k;
  std::vector<Eigen::Triplet<double>> tm;
  tm.reserve(M.nonZeros());
  for (int col = 0; col < M.outerSize(); ++col)
    for (SparseMatrix::InnerIterator it(M, col); it; ++it) {
      const int r = static_cast<int>(it.row());
      tm.emplace_back(3 * pos[r / 3] + r % 3, 3 * pos[col / 3] + col % 3,
                      static_cast<double>(&it.value() - M.valuePtr()));
    }
  s.Mp.resize(M.rows(), M.cols());
  s.Mp.setFromTriplets(tm.begin(), tm.end());
  s.Mp.makeCompressed();
  s.mp_from_m.resize(s.Mp.nonZeros());
  for (long q = 0; q < s.Mp.nonZeros(); ++q) s.mp_from_m[q] = static_cast<int>(s.Mp.valuePtr()[q]);
}

// Where each value of L goes in the block storage (L's pattern is fixed by the analysis).
void block_layout(const SparseMatrix& L, BlockLDLT::Structure& s) {
  using S = BlockLDLT::Structure;
  s.to_vals.assign(L.nonZeros(), S::kSkip);
  s.colptr.assign(s.nb + 1, 0);
  s.rowblk.clear();
  std::map<int, int> slot;  // row block -> index within this column block (ascending rows)
  for (int J = 0; J < s.nb; ++J) {
    slot.clear();
    for (int c = 0; c < 3; ++c)
      for (SparseMatrix::InnerIterator it(L, 3 * J + c); it; ++it)
        if (it.row() / 3 > J) slot.emplace(static_cast<int>(it.row() / 3), 0);
    const long base = static_cast<long>(s.rowblk.size());
    for (auto& [row, index] : slot) {
      index = static_cast<int>(s.rowblk.size() - base);
      s.rowblk.push_back(row);
    }
    for (int c = 0; c < 3; ++c)
      for (SparseMatrix::InnerIterator it(L, 3 * J + c); it; ++it) {
        const int r = static_cast<int>(it.row());
        const long p = &it.value() - L.valuePtr();
        if (r <= 3 * J + c) continue;  // unit diagonal (stored or not)
        if (r / 3 == J) {
          // Within the diagonal block: (1,0), (2,0), (2,1).
          const int k = (r % 3 == 1) ? 0 : (c == 0 ? 1 : 2);
          s.to_vals[p] = -1 - (3L * J + k);
        } else {
          s.to_vals[p] = 9 * (base + slot[r / 3]) + block3::offset(r % 3, c);
        }
      }
    s.colptr[J + 1] = static_cast<int>(s.rowblk.size());
  }
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
  permute_pattern(M, *s);
  s->ldlt.analyzePattern(s->Mp);
  structure_ = s;
  factorize(M);
}

void BlockLDLT::factorize(const SparseMatrix& M) {
  Structure& s = *structure_;
  for (long q = 0; q < s.Mp.nonZeros(); ++q) s.Mp.valuePtr()[q] = M.valuePtr()[s.mp_from_m[q]];
  s.ldlt.factorize(s.Mp);
  require(s.ldlt.info() == Eigen::Success, "BlockLDLT: factorization failed");
  dinv_ = s.ldlt.vectorD().cwiseInverse();
  require(dinv_.allFinite(), "BlockLDLT: singular matrix");
  const SparseMatrix& L = s.ldlt.matrixL().nestedExpression();
  if (s.to_vals.empty()) block_layout(L, s);
  require(static_cast<long>(s.to_vals.size()) == L.nonZeros(), "BlockLDLT: pattern changed");
  ldiag_.assign(3 * static_cast<size_t>(s.nb), 0.0);
  vals_.assign(9 * s.rowblk.size(), 0.0);
  for (long p = 0; p < L.nonZeros(); ++p) {
    const long to = s.to_vals[p];
    if (to >= 0)
      vals_[to] = L.valuePtr()[p];
    else if (to != Structure::kSkip)
      ldiag_[-1 - to] = L.valuePtr()[p];
  }
  w_.resize(M.rows());
  // Check the repacked solve against the matrix itself.
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

void BlockLDLT::solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) const {
  const Structure& s = *structure_;
  const int nb = s.nb;
  // Raw pointers: the stores into w could alias the vectors' own members, which would make
  // the compiler reload them for every block.
  double* w = w_.data();
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
