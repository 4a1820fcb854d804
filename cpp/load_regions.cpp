#include "load_regions.h"

#include <algorithm>
#include <limits>
#include <utility>
#include <vector>

#include "errors.h"

namespace bubble {

namespace {

// The regions grown so far: a union-find whose roots carry their peak, members and core.
class Regions {
 public:
  Regions(const Eigen::Ref<const Eigen::VectorXd>& pd,
          const Eigen::Ref<const Eigen::VectorXd>& force, double k_peak)
      : pd_(pd),
        force_(force),
        k_peak_(k_peak),
        parent_(pd.size(), -1),
        members_(pd.size()),
        core_(pd.size()),
        core_force_(pd.size(), 0.0) {}

  bool seen(int i) const { return parent_[i] >= 0; }

  void add(int i) {
    parent_[i] = i;
    members_[i] = {i};
    core_[i] = {i};
    core_force_[i] = force_(i);
    strongest_ = std::max(strongest_, force_(i));
  }

  int find(int a) {
    while (parent_[a] != a) {
      parent_[a] = parent_[parent_[a]];
      a = parent_[a];
    }
    return a;
  }

  double peak(int root) const { return pd_(root); }  // a root is its region's first node
  double core_force(int root) const { return core_force_[root]; }
  double strongest() const { return strongest_; }  // the largest core force so far
  const std::vector<int>& members(int root) const { return members_[root]; }

  // lo joins hi: lo's core nodes at k_peak of hi's peak join hi's core.
  void merge(int lo, int hi) {
    for (int n : core_[lo]) {
      if (pd_(n) >= k_peak_ * peak(hi)) {
        core_[hi].push_back(n);
        core_force_[hi] += force_(n);
      }
    }
    strongest_ = std::max(strongest_, core_force_[hi]);
    core_[lo].clear();
    if (members_[lo].size() > members_[hi].size()) std::swap(members_[lo], members_[hi]);
    members_[hi].insert(members_[hi].end(), members_[lo].begin(), members_[lo].end());
    members_[lo].clear();
    parent_[lo] = hi;
  }

 private:
  const Eigen::Ref<const Eigen::VectorXd>& pd_;
  const Eigen::Ref<const Eigen::VectorXd>& force_;
  double k_peak_;
  std::vector<int> parent_;
  std::vector<std::vector<int>> members_, core_;
  std::vector<double> core_force_;
  double strongest_ = 0.0;
};

// The support's nodes, highest pd first (ties in index order).
std::vector<int> descending(const Eigen::Ref<const Eigen::VectorXd>& pd,
                            const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& s) {
  std::vector<int> order;
  for (int i = 0; i < pd.size(); ++i)
    if (s(i)) order.push_back(i);
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return pd(a) > pd(b); });
  return order;
}

}  // namespace

LoadRegions load_regions(const Eigen::Ref<const Eigen::VectorXd>& pd,
                         const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support,
                         const Eigen::Ref<const Eigen::VectorXi>& adjacency_ptr,
                         const Eigen::Ref<const Eigen::VectorXi>& adjacency_idx,
                         const Eigen::Ref<const Eigen::VectorXd>& force, double k_peak,
                         double k_load, double join_pa) {
  const Eigen::Index n = pd.size();
  require(support.size() == n && force.size() == n, "pd, support and force must have N entries");
  require(adjacency_ptr.size() == n + 1, "adjacency_ptr must have N + 1 entries");
  require(adjacency_ptr(0) == 0 && adjacency_ptr(n) == adjacency_idx.size(),
          "adjacency_ptr does not match adjacency_idx");
  require(
      adjacency_idx.size() == 0 || (adjacency_idx.minCoeff() >= 0 && adjacency_idx.maxCoeff() < n),
      "adjacency_idx out of range");

  LoadRegions out{Eigen::VectorXd::Constant(n, std::numeric_limits<double>::infinity()),
                  Eigen::VectorXi::Constant(n, -1)};
  Regions regions(pd, force, k_peak);
  const std::vector<int> order = descending(pd, support);
  for (int i : order) {
    regions.add(i);
    for (int e = adjacency_ptr(i); e < adjacency_ptr(i + 1); ++e) {
      const int j = adjacency_idx(e);
      if (!regions.seen(j)) continue;
      int lo = regions.find(i), hi = regions.find(j);
      if (lo == hi) continue;
      if (regions.peak(lo) >= regions.peak(hi)) std::swap(lo, hi);
      const bool apart = pd(i) < k_peak * regions.peak(lo) && pd(i) < join_pa &&
                         regions.core_force(lo) >= k_load * regions.strongest();
      if (apart) {
        for (int node : regions.members(lo)) {
          if (out.label(node) >= 0) continue;
          out.peak(node) = regions.peak(lo);
          out.label(node) = lo;
        }
      }
      regions.merge(lo, hi);
    }
  }
  for (int node : order) {
    if (out.label(node) >= 0) continue;
    const int root = regions.find(node);
    out.peak(node) = regions.peak(root);
    out.label(node) = root;
  }
  return out;
}

}  // namespace bubble
