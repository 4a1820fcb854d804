// Linear plane-stress membrane model of the bubble (docs/method.md, "Inflated membrane model").
#pragma once

#include <Eigen/Core>
#include <Eigen/SparseCore>

namespace bubble {

using RowMatrixX3d = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
using RowMatrixX3i = Eigen::Matrix<int, Eigen::Dynamic, 3, Eigen::RowMajor>;
using SparseMatrixd = Eigen::SparseMatrix<double>;  // column-major

// Membrane of constant-strain triangles (CST) built once per mesh and material.
//
// Units: vertices in metres, E in pascals, thickness in metres, so K is in N/m, areas in m^2
// and forces in newtons. Sign convention: F_ext(U, dp) = K U - dp * a_i * n_i.
class MembraneModel {
 public:
  // Throws InputError on bad shapes, out-of-range indices, degenerate triangles or invalid
  // material parameters (E > 0, thickness > 0, -1 < nu <= 0.5).
  MembraneModel(const Eigen::Ref<const RowMatrixX3d>& vertices,
                const Eigen::Ref<const RowMatrixX3i>& triangles, double E, double nu,
                double thickness);

  int n_nodes() const { return static_cast<int>(areas_.size()); }
  // 3N x 3N symmetric positive semi-definite stiffness, dof order (x0, y0, z0, x1, ...).
  const SparseMatrixd& stiffness() const { return K_; }
  // Lumped areas a_i: a third of every incident triangle's area (m^2).
  const Eigen::VectorXd& areas() const { return areas_; }
  // Area-weighted outward unit normals n_i (N x 3).
  const RowMatrixX3d& normals() const { return normals_; }
  // a_i * n_i (N x 3, m^2): the pressure force per pascal.
  const RowMatrixX3d& area_normals() const { return area_normals_; }

  // F_ext = K U - dp a n (N x 3, newtons). Throws InputError on bad shape or non-finite input.
  RowMatrixX3d external_forces(const Eigen::Ref<const RowMatrixX3d>& U, double dp) const;

  // Adds dK (3N x 3N, N/m, finite) to the stiffness: the inflation terms of a prestressed
  // membrane (geometric stiffness of its tension, load stiffness of the rest pressure), which
  // need not be symmetric. Throws InputError on a wrong size or a non-finite entry.
  void add_stiffness(const SparseMatrixd& dK);

 private:
  Eigen::VectorXd areas_;
  RowMatrixX3d normals_;
  RowMatrixX3d area_normals_;
  SparseMatrixd K_;
};

// Normal pressure p_i = -n_i . F_i / a_i (Pa, inward positive).
Eigen::VectorXd normal_pressure(const Eigen::Ref<const RowMatrixX3d>& forces,
                                const Eigen::Ref<const Eigen::VectorXd>& areas,
                                const Eigen::Ref<const RowMatrixX3d>& normals);

// Contact mask: p_v > max(k_const, k_linear * (a . p) / sum(a)).
Eigen::Matrix<bool, Eigen::Dynamic, 1> contact_mask(
    const Eigen::Ref<const Eigen::VectorXd>& normal_pressure,
    const Eigen::Ref<const Eigen::VectorXd>& areas, double k_const, double k_linear);

// Net force of the object on the membrane: sum of F_i over nodes with interior[i] true.
Eigen::Vector3d net_force(const Eigen::Ref<const RowMatrixX3d>& forces,
                          const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& interior);

}  // namespace bubble
