// Node values checked against their neighbours on the mesh graph: a node whose value stands
// apart from the component-wise median of its measured neighbours is an outlier (a tracking
// or depth error the membrane, which is smooth, cannot make).
#pragma once

#include <Eigen/Core>
#include <cstdint>

namespace bubble {

using RowMatrixX3d = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
using NeighbourTable = Eigen::Matrix<std::int64_t, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using BoolVector = Eigen::Matrix<bool, Eigen::Dynamic, 1>;

// Measured nodes whose value U_i (N x 3) lies further than max(tol, relative_tol |m_i|)
// (Euclidean) from m_i, the component-wise median of its measured neighbours, for nodes with
// at least two of them. relative_tol lets a node in a dent stand apart from its neighbours by
// a share of their own displacement (a pin's tip); tol holds where they have not moved.
// neighbours: N x W node indices, rows padded with negative entries; an even count takes the
// mean of the two middle values. Throws InputError on mismatched sizes or an index >= N.
BoolVector neighbour_outliers(const Eigen::Ref<const RowMatrixX3d>& U,
                              const Eigen::Ref<const BoolVector>& measured,
                              const Eigen::Ref<const NeighbourTable>& neighbours, double tol,
                              double relative_tol = 0.0);

}  // namespace bubble
