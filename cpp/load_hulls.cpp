#include "load_hulls.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <map>
#include <string>
#include <vector>

#include "errors.h"

namespace bubble {

namespace {
using Points3 = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
using Point2 = Eigen::Vector2d;

// z of (b - a) x (c - a): > 0 when a, b, c turn counter-clockwise.
double turn(const Point2& a, const Point2& b, const Point2& c) {
  return (b.x() - a.x()) * (c.y() - a.y()) - (b.y() - a.y()) * (c.x() - a.x());
}

// The convex hull of pts, counter-clockwise, without collinear points (Andrew's monotone chain).
std::vector<Point2> convex_hull(std::vector<Point2> pts) {
  std::sort(pts.begin(), pts.end(), [](const Point2& a, const Point2& b) {
    return a.x() < b.x() || (a.x() == b.x() && a.y() < b.y());
  });
  std::vector<Point2> hull;
  const auto chain = [&](auto first, auto last) {
    const std::size_t start = hull.size();
    for (auto it = first; it != last; ++it) {
      while (hull.size() >= start + 2 && turn(hull[hull.size() - 2], hull.back(), *it) <= 0)
        hull.pop_back();
      hull.push_back(*it);
    }
    hull.pop_back();  // the chain's last point starts the other chain
  };
  chain(pts.begin(), pts.end());
  chain(pts.rbegin(), pts.rend());
  return hull;
}

// Inside (or on) every counter-clockwise edge; 1e-12 m^2 admits nodes on the hull.
bool inside(const std::vector<Point2>& hull, const Point2& q) {
  for (std::size_t k = 0; k < hull.size(); ++k)
    if (turn(hull[k], hull[(k + 1) % hull.size()], q) < -1e-12) return false;
  return true;
}

// Two unit vectors spanning the plane normal to n.
Eigen::Matrix<double, 3, 2> plane_basis(Eigen::Vector3d n) {
  n.normalize();
  const Eigen::Vector3d axis =
      std::abs(n.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  const Eigen::Vector3d e1 = n.cross(axis).normalized();
  Eigen::Matrix<double, 3, 2> basis;
  basis << e1, n.cross(e1);
  return basis;
}
}  // namespace

LoadHulls fill_load_hulls(const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& contact,
                          const Eigen::Ref<const Eigen::VectorXi>& label,
                          const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& support,
                          const Eigen::Ref<const Points3>& vertices,
                          const Eigen::Ref<const Points3>& normals) {
  const Eigen::Index n = contact.size();
  const std::string N = std::to_string(n);
  require(label.size() == n && support.size() == n, "label and support must have N = " + N);
  require(vertices.rows() == n && normals.rows() == n,
          "vertices and normals must be N = " + N + " x 3");
  LoadHulls out{contact, label};
  std::map<int, std::vector<Eigen::Index>> loads;  // ordered: filled in increasing label order
  std::vector<Eigen::Index> free;
  for (Eigen::Index i = 0; i < n; ++i) {
    if (contact(i) && label(i) >= 0) loads[label(i)].push_back(i);
    if (support(i) && !contact(i)) free.push_back(i);
  }
  for (const auto& [load, nodes] : loads) {
    if (nodes.size() < 3) continue;
    Eigen::Vector3d origin = Eigen::Vector3d::Zero(), normal = Eigen::Vector3d::Zero();
    for (const Eigen::Index i : nodes) {
      origin += vertices.row(i).transpose();
      normal += normals.row(i).transpose();
    }
    origin /= static_cast<double>(nodes.size());
    // Only free nodes near the load's bounding sphere can be inside its hull (x 1.5 in the
    // squared radius: a node's offset along the normal is not in the hull's plane).
    double reach = 0.0;
    for (const Eigen::Index i : nodes)
      reach = std::max(reach, (vertices.row(i).transpose() - origin).squaredNorm());
    reach *= 1.5;
    const Eigen::Matrix<double, 3, 2> basis = plane_basis(normal);
    std::vector<Point2> pts;
    for (const Eigen::Index i : nodes)
      pts.emplace_back(basis.transpose() * (vertices.row(i).transpose() - origin));
    const std::vector<Point2> hull = convex_hull(pts);
    if (hull.size() < 3) continue;  // collinear: no area to fill
    for (const Eigen::Index i : free) {
      const Eigen::Vector3d d = vertices.row(i).transpose() - origin;
      if (out.contact(i) || d.squaredNorm() > reach) continue;
      if (inside(hull, basis.transpose() * d)) {
        out.contact(i) = true;
        out.label(i) = load;
      }
    }
  }
  return out;
}

}  // namespace bubble
