// The contact rule's loads: which peak each support node's contact threshold refers to.
//
// The support's nodes join from the highest disc pressure pd down, a union-find over the mesh
// edges within the support. Where two regions meet at a node below k_peak times the lower
// region's peak, the lower one is a load of its own (its nodes keep its peak and its label)
// when its core force (its nodes at k_peak of its peak) is at least k_load times the strongest
// core force so far (the main load's, by then). Otherwise, and where they meet above that level,
// they are one load, measured against the higher peak. Two pins pressing apart meet far below
// either peak; the bumps around one dent meet near theirs or carry little force. Regions that
// meet where pd is at least join_pa are one load too: a flat face's loaded edges meet across
// its middle, which carries the gas's gauge pressure, while free membrane carries none.
#pragma once

#include <Eigen/Core>
#include <limits>

namespace bubble {

struct LoadRegions {
  Eigen::VectorXd peak;   // (N,) Pa: the peak of each support node's load; +inf off the support
  Eigen::VectorXi label;  // (N,) the load's region (a node index); -1 off the support
};

// pd: (N,) Pa, disc-averaged normal pressure; support: (N,) the nodes that carry force;
// adjacency_ptr / adjacency_idx: the mesh's N x N edge adjacency in CSR form; force: (N,) N,
// each node's normal force where it passes the paper's threshold, else 0; join_pa: Pa (see
// above; inf: never). Throws InputError on
// inconsistent shapes or an index out of range.
LoadRegions load_regions(const Eigen::Ref<const Eigen::VectorXd>& pd,
                         const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support,
                         const Eigen::Ref<const Eigen::VectorXi>& adjacency_ptr,
                         const Eigen::Ref<const Eigen::VectorXi>& adjacency_idx,
                         const Eigen::Ref<const Eigen::VectorXd>& force, double k_peak,
                         double k_load, double join_pa = std::numeric_limits<double>::infinity());

}  // namespace bubble
