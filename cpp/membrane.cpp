#include "membrane.h"

#include <Eigen/Geometry>
#include <cmath>
#include <string>
#include <vector>

#include "errors.h"

namespace bubble {

MembraneModel::MembraneModel(const Eigen::Ref<const RowMatrixX3d>& vertices,
                             const Eigen::Ref<const RowMatrixX3i>& triangles, double E, double nu,
                             double thickness) {
  const Eigen::Index n = vertices.rows();
  require(n >= 3, "vertices: need at least 3 nodes, got " + std::to_string(n));
  require(triangles.rows() >= 1, "triangles: need at least one triangle");
  require(vertices.allFinite(), "vertices: contains NaN or inf");
  require(std::isfinite(E) && E > 0,
          "E must be a finite positive Young's modulus (Pa), got " + std::to_string(E));
  require(std::isfinite(nu) && nu > -1.0 && nu <= 0.5,
          "nu must be in (-1, 0.5], got " + std::to_string(nu));
  require(std::isfinite(thickness) && thickness > 0,
          "thickness must be finite and positive (m), got " + std::to_string(thickness));
  for (Eigen::Index t = 0; t < triangles.rows(); ++t)
    for (int c = 0; c < 3; ++c)
      require(triangles(t, c) >= 0 && triangles(t, c) < n,
              "triangle " + std::to_string(t) + " indexes vertex " +
                  std::to_string(triangles(t, c)) + " outside 0.." + std::to_string(n - 1));

  areas_ = Eigen::VectorXd::Zero(n);
  area_normals_ = RowMatrixX3d::Zero(n, 3);
  Eigen::Matrix3d D;
  D << 1, nu, 0, nu, 1, 0, 0, 0, (1 - nu) / 2;
  D *= E / (1 - nu * nu);

  std::vector<Eigen::Triplet<double>> trip;
  trip.reserve(static_cast<size_t>(triangles.rows()) * 81);
  for (Eigen::Index t = 0; t < triangles.rows(); ++t) {
    const int ids[3] = {triangles(t, 0), triangles(t, 1), triangles(t, 2)};
    const Eigen::Vector3d o = vertices.row(ids[0]).transpose();
    const Eigen::Vector3d p = vertices.row(ids[1]).transpose();
    const Eigen::Vector3d q = vertices.row(ids[2]).transpose();
    const Eigen::Vector3d cross = (p - o).cross(q - o);
    const double area = 0.5 * cross.norm();
    const double scale = std::max((p - o).squaredNorm(), (q - o).squaredNorm());
    require(area > 1e-12 * scale && scale > 0,
            "triangle " + std::to_string(t) + " is degenerate (zero area)");
    for (int c = 0; c < 3; ++c) {
      areas_(ids[c]) += area / 3.0;
      area_normals_.row(ids[c]) += cross.transpose();  // area-weighted normal sum
    }
    // In-plane frame: i along o->p, k the triangle normal, j = k x i.
    const Eigen::Vector3d ih = (p - o).normalized();
    const Eigen::Vector3d kh = cross.normalized();
    const Eigen::Vector3d jh = kh.cross(ih);
    Eigen::Matrix<double, 2, 3> Rt;
    Rt.row(0) = ih.transpose();
    Rt.row(1) = jh.transpose();
    double x[3], y[3];
    for (int c = 0; c < 3; ++c) {
      const Eigen::Vector2d l = Rt * (vertices.row(ids[c]).transpose() - o);
      x[c] = l(0);
      y[c] = l(1);
    }
    Eigen::Matrix<double, 3, 6> B = Eigen::Matrix<double, 3, 6>::Zero();
    const double twoA = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0]);
    for (int c = 0; c < 3; ++c) {
      const int j = (c + 1) % 3, k = (c + 2) % 3;
      const double b = (y[j] - y[k]) / twoA, cc = (x[k] - x[j]) / twoA;
      B(0, 2 * c) = b;
      B(1, 2 * c + 1) = cc;
      B(2, 2 * c) = cc;
      B(2, 2 * c + 1) = b;
    }
    const Eigen::Matrix<double, 6, 6> Ke2 = thickness * area * B.transpose() * D * B;
    Eigen::Matrix<double, 6, 9> R = Eigen::Matrix<double, 6, 9>::Zero();
    for (int c = 0; c < 3; ++c) R.block<2, 3>(2 * c, 3 * c) = Rt;
    const Eigen::Matrix<double, 9, 9> Ke = R.transpose() * Ke2 * R;
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b)
        for (int r = 0; r < 3; ++r)
          for (int s = 0; s < 3; ++s)
            trip.emplace_back(3 * ids[a] + r, 3 * ids[b] + s, Ke(3 * a + r, 3 * b + s));
  }
  for (Eigen::Index i = 0; i < n; ++i)
    require(areas_(i) > 0, "vertex " + std::to_string(i) + " is not referenced by any triangle");
  normals_.resize(n, 3);
  for (Eigen::Index i = 0; i < n; ++i) {
    normals_.row(i) = area_normals_.row(i).normalized();
    // docs/method.md: the pressure force is dp * a_i * n_i with the lumped area and unit normal.
    area_normals_.row(i) = areas_(i) * normals_.row(i);
  }
  K_.resize(3 * n, 3 * n);
  K_.setFromTriplets(trip.begin(), trip.end());
  K_.makeCompressed();
}

void MembraneModel::add_stiffness(const SparseMatrixd& dK) {
  const Eigen::Index m = 3 * static_cast<Eigen::Index>(n_nodes());
  require(dK.rows() == m && dK.cols() == m,
          "stiffness increment must be " + std::to_string(m) + " x " + std::to_string(m));
  for (Eigen::Index k = 0; k < dK.outerSize(); ++k)
    for (SparseMatrixd::InnerIterator it(dK, k); it; ++it)
      require(std::isfinite(it.value()), "stiffness increment has a non-finite entry");
  SparseMatrixd sum = K_ + dK;
  sum.makeCompressed();
  K_ = std::move(sum);
}

RowMatrixX3d MembraneModel::external_forces(const Eigen::Ref<const RowMatrixX3d>& U,
                                            double dp) const {
  require(U.rows() == n_nodes(), "U must be N x 3 with N = " + std::to_string(n_nodes()) +
                                     ", got " + std::to_string(U.rows()) + " rows");
  require(U.allFinite(), "U contains NaN or inf");
  require(std::isfinite(dp), "dp is NaN or inf");
  RowMatrixX3d F(n_nodes(), 3);
  Eigen::Map<Eigen::VectorXd> f(F.data(), F.size());
  f.noalias() = K_ * Eigen::Map<const Eigen::VectorXd>(U.data(), U.size());
  F -= dp * area_normals_;
  return F;
}

Eigen::VectorXd normal_pressure(const Eigen::Ref<const RowMatrixX3d>& forces,
                                const Eigen::Ref<const Eigen::VectorXd>& areas,
                                const Eigen::Ref<const RowMatrixX3d>& normals) {
  require(forces.rows() == areas.size() && normals.rows() == areas.size(),
          "forces, areas and normals must have the same number of nodes");
  return -(forces.cwiseProduct(normals).rowwise().sum()).cwiseQuotient(areas);
}

Eigen::Matrix<bool, Eigen::Dynamic, 1> contact_mask(
    const Eigen::Ref<const Eigen::VectorXd>& normal_pressure,
    const Eigen::Ref<const Eigen::VectorXd>& areas, double k_const, double k_linear) {
  require(normal_pressure.size() == areas.size(), "pressure and areas differ in length");
  const double mean = areas.dot(normal_pressure) / areas.sum();
  const double thresh = std::max(k_const, k_linear * mean);
  return (normal_pressure.array() > thresh).matrix();
}

Eigen::Vector3d net_force(
    const Eigen::Ref<const RowMatrixX3d>& forces,
    const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& interior) {
  require(forces.rows() == interior.size(), "forces and interior mask differ in length");
  Eigen::Vector3d s = Eigen::Vector3d::Zero();
  for (Eigen::Index i = 0; i < forces.rows(); ++i)
    if (interior(i)) s += forces.row(i).transpose();
  return s;
}

}  // namespace bubble
