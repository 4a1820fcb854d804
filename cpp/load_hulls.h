// The contact rule's last step: each load's contact filled to the convex hull of its nodes.
//
// A rigid convex indenter touches a convex region of the membrane, but the k_peak rule keeps a
// load's firmest nodes: on a flat face its edges, whose bent membrane carries line loads, while
// the face's middle carries only the gas's gauge pressure. So the support nodes inside the
// convex hull of a load's contact nodes (in the plane normal to their mean normal) join that
// load. Loads of fewer than three nodes, or collinear ones, stay as they are; loads are filled
// in increasing label order, a node once filled is not taken by a later load.
#pragma once

#include <Eigen/Core>

namespace bubble {

struct LoadHulls {
  Eigen::Matrix<bool, Eigen::Dynamic, 1> contact;  // (N,) the contact nodes after the fill
  Eigen::VectorXi label;                           // (N,) each contact node's load, else -1
};

// contact: (N,) the rule's contact nodes; label: (N,) their loads (>= 0), -1 elsewhere;
// support: (N,) the nodes that may be filled; vertices, normals: (N, 3) the untouched mesh (m)
// and its outward unit normals. Throws InputError on inconsistent shapes.
LoadHulls fill_load_hulls(
    const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& contact,
    const Eigen::Ref<const Eigen::VectorXi>& label,
    const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support,
    const Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>>& vertices,
    const Eigen::Ref<const Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>>& normals);

}  // namespace bubble
