#include "neighbour_median.h"

#include <algorithm>
#include <cmath>
#include <string>
#include <vector>

#include "errors.h"

namespace bubble {

namespace {
// The median of v (n >= 1 values, reordered): the middle value, or the mean of the two.
double median(std::vector<double>& v) {
  const auto n = static_cast<std::ptrdiff_t>(v.size());
  const auto hi = v.begin() + n / 2;
  std::nth_element(v.begin(), hi, v.end());
  if (n % 2 == 1) return *hi;
  const double lo = *std::max_element(v.begin(), hi);
  return 0.5 * (lo + *hi);
}
}  // namespace

BoolVector neighbour_outliers(const Eigen::Ref<const RowMatrixX3d>& U,
                              const Eigen::Ref<const BoolVector>& measured,
                              const Eigen::Ref<const NeighbourTable>& neighbours, double tol,
                              double relative_tol) {
  const Eigen::Index n = U.rows();
  require(measured.size() == n, "measured must have N = " + std::to_string(n) + " entries");
  require(neighbours.rows() == n, "neighbours must have N = " + std::to_string(n) + " rows");
  require((neighbours.array() < n).all(), "neighbour index out of range");
  BoolVector out = BoolVector::Zero(n);
  std::vector<int> ids;
  std::vector<double> v;
  for (Eigen::Index i = 0; i < n; ++i) {
    if (!measured(i)) continue;
    ids.clear();
    for (Eigen::Index k = 0; k < neighbours.cols(); ++k) {
      const std::int64_t j = neighbours(i, k);
      if (j >= 0 && measured(j)) ids.push_back(static_cast<int>(j));
    }
    if (ids.size() < 2) continue;
    Eigen::RowVector3d med;
    for (int c = 0; c < 3; ++c) {
      v.clear();
      for (const int j : ids) v.push_back(U(j, c));
      med(c) = median(v);
    }
    out(i) = (U.row(i) - med).norm() > std::max(tol, relative_tol * med.norm());
  }
  return out;
}

}  // namespace bubble
