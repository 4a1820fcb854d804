#include "group_lasso.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <vector>

#include "errors.h"

namespace bubble {

namespace {
using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}
// rho moves on a grid of quarter decades so that factorizations can be cached and reused.
constexpr double kRhoGridPerDecade = 4.0;
constexpr int kMaxCachedFactors = 12;
// Before any solution exists, the solution's force scale is guessed from the raw nodal forces
// (measured: about 1e-3 of them on untouched frames, 1e-1 in firm contact); later it is
// floored so that an all-zero solution cannot send rho to infinity.
constexpr double kFirstForceRatio = 3e-3;
constexpr double kMinForceRatio = 1e-4;

// Type-II Anderson acceleration of a fixed-point map u -> G(u) (Walker & Ni), with a small
// Tikhonov term and a restart whenever the fixed-point residual jumps.
class Anderson {
 public:
  Anderson(int mem, Eigen::Index dim)
      : mem_(mem), dF_(dim, mem), dG_(dim, mem), H_(Eigen::MatrixXd::Zero(mem, mem)) {}
  void reset() {
    count_ = 0;
    have_prev_ = false;
  }
  // u: the input of G; g: G(u) on entry, the accelerated next iterate on exit.
  void step(const Eigen::VectorXd& u, Eigen::VectorXd& g) {
    f_ = g - u;
    const double fn = f_.squaredNorm();
    if (have_prev_ && fn > 4.0 * fprev_norm_) count_ = 0;  // diverging: restart the memory
    if (have_prev_) {
      const int col = static_cast<int>(count_ % mem_);
      dF_.col(col) = f_ - f_prev_;
      dG_.col(col) = g - g_prev_;
      ++count_;
      // Keep the Gram matrix of the stored differences up to date (one new row/column).
      const int k = static_cast<int>(std::min<long>(count_, mem_));
      for (int j = 0; j < k; ++j) H_(col, j) = H_(j, col) = dF_.col(col).dot(dF_.col(j));
    }
    f_prev_ = f_;
    g_prev_ = g;
    fprev_norm_ = fn;
    have_prev_ = true;
    const int k = static_cast<int>(std::min<long>(count_, mem_));
    if (k == 0) return;
    Eigen::MatrixXd H = H_.topLeftCorner(k, k);
    H.diagonal().array() += 1e-10 * H.diagonal().maxCoeff() + 1e-300;
    rhs_.noalias() = dF_.leftCols(k).transpose() * f_;
    const Eigen::VectorXd gamma = H.ldlt().solve(rhs_);
    if (!gamma.allFinite()) return;
    g.noalias() -= dG_.leftCols(k) * gamma;
  }

 private:
  int mem_;
  long count_ = 0;
  bool have_prev_ = false;
  double fprev_norm_ = 0;
  Eigen::MatrixXd dF_, dG_, H_;
  Eigen::VectorXd f_, f_prev_, g_prev_, rhs_;
};
}  // namespace

void SolverSettings::validate() const {
  require(std::isfinite(rho) && rho > 0, "rho must be positive");
  require(std::isfinite(sigma) && sigma >= 0, "sigma must be >= 0");
  require(alpha > 0 && alpha < 2, "alpha must be in (0, 2)");
  require(adaptive_rho_tolerance >= 1, "adaptive_rho_tolerance must be >= 1");
  require(adaptive_rho_interval >= 1, "adaptive_rho_interval must be >= 1");
  require(eps_abs >= 0 && eps_rel >= 0 && (eps_abs > 0 || eps_rel > 0),
          "eps_abs and eps_rel must be >= 0 and not both zero");
  require(max_iter >= 1, "max_iter must be >= 1");
  require(check_interval >= 1, "check_interval must be >= 1");
  require(std::isfinite(time_limit) && time_limit >= 0, "time_limit must be >= 0 (0 = none)");
  require(scaling_iter >= 0, "scaling_iter must be >= 0");
  require(anderson_memory >= 0 && anderson_memory <= 50, "anderson_memory must be in 0..50");
}

std::string to_string(SolverStatus s) {
  switch (s) {
    case SolverStatus::solved:
      return "solved";
    case SolverStatus::max_iter_reached:
      return "max_iter_reached";
    case SolverStatus::time_limit_reached:
      return "time_limit_reached";
    case SolverStatus::non_finite_input:
      return "non_finite_input";
  }
  return "unknown";
}

GroupLassoSolver::GroupLassoSolver(const SparseMatrixd& K,
                                   const Eigen::Ref<const RowMatrixX3d>& area_normals,
                                   const Eigen::Ref<const Eigen::VectorXi>& boundary, double k_f,
                                   double k_u, const SolverSettings& settings)
    : settings_(settings) {
  settings.validate();
  n_ = static_cast<int>(area_normals.rows());
  require(n_ >= 1, "area_normals must be N x 3 with N >= 1");
  require(K.rows() == 3 * n_ && K.cols() == 3 * n_,
          "K must be 3N x 3N with N = " + std::to_string(n_));
  require(area_normals.allFinite(), "area_normals contains NaN or inf");
  is_rim_ = Eigen::VectorXi::Zero(n_);
  for (Eigen::Index i = 0; i < boundary.size(); ++i) {
    require(boundary(i) >= 0 && boundary(i) < n_,
            "boundary index " + std::to_string(boundary(i)) + " out of range");
    is_rim_(boundary(i)) = 1;
  }
  require(is_rim_.sum() >= 1, "boundary must name at least one rim node");
  nf_ = n_ - is_rim_.sum();
  require(nf_ >= 1, "mesh has no free (non-rim) node");
  free_.resize(nf_);
  Eigen::VectorXi col_of = Eigen::VectorXi::Constant(n_, -1);
  for (int i = 0, j = 0; i < n_; ++i)
    if (!is_rim_(i)) {
      free_(j) = i;
      col_of(i) = j++;
    }
  std::vector<Eigen::Triplet<double>> trip;
  for (int col = 0; col < K.outerSize(); ++col) {
    const int node = col / 3;
    if (is_rim_(node)) continue;
    const int c = 3 * col_of(node) + col % 3;
    for (SparseMatrixd::InnerIterator it(K, col); it; ++it) {
      require(std::isfinite(it.value()), "K contains NaN or inf");
      trip.emplace_back(static_cast<int>(it.row()), c, it.value());
    }
  }
  A_.resize(3 * n_, 3 * nf_);
  A_.setFromTriplets(trip.begin(), trip.end());
  A_.makeCompressed();
  an_ = area_normals;
  set_weights(k_f, k_u);
}

void GroupLassoSolver::set_weights(double k_f, double k_u) {
  require(std::isfinite(k_f) && k_f > 0, "k_f must be finite and positive");
  require(std::isfinite(k_u) && k_u > 0, "k_u must be finite and positive");
  k_f_ = k_f;
  k_u_ = k_u;
  c_ = k_u / n_;
  const double n_rim = n_ - nf_;
  w_.resize(n_);
  for (int i = 0; i < n_; ++i) w_(i) = is_rim_(i) ? k_f * n_rim / n_ : k_f;
  setup();
}

void GroupLassoSolver::set_settings(const SolverSettings& settings) {
  settings.validate();
  const bool rescale =
      settings.rho != settings_.rho || settings.scaling_iter != settings_.scaling_iter;
  const bool resigma = settings.sigma != settings_.sigma;
  settings_ = settings;
  fresh_ = false;
  if (rescale || resigma) setup();
}

void GroupLassoSolver::setup() {
  const auto t0 = Clock::now();
  const int m = 3 * n_, nfd = 3 * nf_;
  // Ruiz equilibration of [[P, A^T], [A, 0]] with one factor per node (keeps the block norms
  // of the group lasso intact), P = 2 c I.
  Eigen::VectorXd d = Eigen::VectorXd::Ones(nf_), e = Eigen::VectorXd::Ones(n_);
  for (int it = 0; it < settings_.scaling_iter; ++it) {
    Eigen::VectorXd cn(nf_), rn = Eigen::VectorXd::Zero(n_);
    for (int j = 0; j < nf_; ++j) cn(j) = 2 * c_ * d(j) * d(j);
    for (int col = 0; col < nfd; ++col)
      for (SparseMatrixd::InnerIterator a(A_, col); a; ++a) {
        const double v = std::abs(a.value()) * e(a.row() / 3) * d(col / 3);
        cn(col / 3) = std::max(cn(col / 3), v);
        rn(a.row() / 3) = std::max(rn(a.row() / 3), v);
      }
    for (int j = 0; j < nf_; ++j) d(j) /= std::sqrt(std::max(cn(j), 1e-300));
    for (int i = 0; i < n_; ++i)
      if (rn(i) > 0) e(i) /= std::sqrt(rn(i));
  }
  D_.resize(nfd);
  E_.resize(m);
  for (int j = 0; j < nfd; ++j) D_(j) = d(j / 3);
  for (int i = 0; i < m; ++i) E_(i) = e(i / 3);
  Dinv_ = D_.cwiseInverse();
  Einv_ = E_.cwiseInverse();
  Ah_ = E_.asDiagonal() * A_ * D_.asDiagonal();
  Ah_.makeCompressed();
  AhT_ = Ah_.transpose();
  AhT_.makeCompressed();
  AtA_ = (AhT_ * Ah_).pruned();
  Ab_ = BlockMatrix3(Ah_);
  AtA_.makeCompressed();
  // Cost scale: the mean of P's diagonal becomes one (OSQP's rule without a linear term).
  Pd_ = 2 * c_ * D_.cwiseAbs2();
  s_ = 1.0 / Pd_.mean();
  Pd_ *= s_;
  wh_.resize(n_);
  for (int i = 0; i < n_; ++i) wh_(i) = s_ * w_(i) / e(i);
  factors_.clear();
  rho_set_ = false;
  force_scale_ = 0;
  fresh_ = false;
  if (have_data_) {
    RowMatrixX3d U = U_;
    update(U, dp_);
  }
  setup_ms_ = ms_since(t0);
}

double GroupLassoSolver::rho_of(int idx) const { return std::pow(10.0, idx / kRhoGridPerDecade); }

const BlockLDLT& GroupLassoSolver::factor(int idx, int* count) {
  auto it = factors_.find(idx);
  if (it != factors_.end()) return *it->second;
  if (static_cast<int>(factors_.size()) >= kMaxCachedFactors) {
    // Drop the cached factor farthest from the requested rho.
    auto far = factors_.begin();
    if (std::abs(factors_.rbegin()->first - idx) > std::abs(far->first - idx))
      far = std::prev(factors_.end());
    factors_.erase(far);
  }
  SparseMatrixd M = AtA_ * rho_of(idx);
  for (int j = 0; j < M.cols(); ++j) M.coeffRef(j, j) += Pd_(j) + settings_.sigma;
  const auto t0 = Clock::now();
  auto f = std::make_unique<BlockLDLT>(M);
  factor_ms_ += ms_since(t0);
  ++*count;
  return *(factors_[idx] = std::move(f));
}

void GroupLassoSolver::update(const Eigen::Ref<const RowMatrixX3d>& U, double dp) {
  require(U.rows() == n_, "U must be N x 3 with N = " + std::to_string(n_) + ", got " +
                              std::to_string(U.rows()) + " rows");
  for (Eigen::Index i = 0; i < U.rows(); ++i)
    require(U.row(i).allFinite(), "U has NaN or inf at node " + std::to_string(i));
  require(std::isfinite(dp), "dp is NaN or inf");
  if (fresh_ && dp == dp_ && U_.rows() == U.rows() && U_ == U) return;
  fresh_ = false;
  U_ = U;
  dp_ = dp;
  Eigen::VectorXd uf(3 * nf_);
  for (int j = 0; j < nf_; ++j) uf.segment<3>(3 * j) = U_.row(free_(j)).transpose();
  Eigen::VectorXd b = A_ * uf;
  b -= dp * Eigen::Map<const Eigen::VectorXd>(an_.data(), an_.size());
  bh_ = E_.cwiseProduct(b);
  rim_const_ = 0;
  for (int i = 0; i < n_; ++i)
    if (is_rim_(i)) rim_const_ += c_ * U_.row(i).squaredNorm();
  have_data_ = true;
}

void GroupLassoSolver::warm_start(const Eigen::Ref<const RowMatrixX3d>& V,
                                  const Eigen::Ref<const RowMatrixX3d>& dual) {
  require(V.rows() == n_ && dual.rows() == n_, "warm start arrays must be N x 3");
  require(V.allFinite() && dual.allFinite(), "warm start arrays contain NaN or inf");
  V_prev_ = V;
  dual_prev_ = dual;
  have_prev_ = true;
  fresh_ = false;
}

void GroupLassoSolver::cold_start() {
  have_prev_ = false;
  fresh_ = false;
}

void GroupLassoSolver::prox(const Eigen::VectorXd& v, double rho, Eigen::VectorXd& out) const {
  // prox of sum_i wh_i ||z_i + bh_i|| / rho: shrink u = v + b blockwise, shift back.
  for (int i = 0; i < n_; ++i) {
    const Eigen::Vector3d u = v.segment<3>(3 * i) + bh_.segment<3>(3 * i);
    const double nu = u.norm(), t = wh_(i) / rho;
    const double k = nu > t ? 1.0 - t / nu : 0.0;
    out.segment<3>(3 * i) = k * u - bh_.segment<3>(3 * i);
  }
}

SolverResult GroupLassoSolver::solve() {
  require(have_data_, "solve() called before update(U, dp)");
  const auto t0 = Clock::now();
  if (fresh_) {
    SolverResult again = last_;
    again.info.iterations = 0;
    again.info.factorizations = 0;
    again.info.setup_time_ms = 0;
    again.info.solve_time_ms = ms_since(t0);
    return again;
  }
  const int m = 3 * n_, nfd = 3 * nf_;
  SolverResult res;
  SolverInfo& info = res.info;
  factor_ms_ = 0;
  res.dU.setZero(n_, 3);
  res.dual.setZero(n_, 3);
  if (!bh_.allFinite()) {
    // Finite U and dp can still overflow with extreme stiffness.
    info.status = SolverStatus::non_finite_input;
    info.objective = std::numeric_limits<double>::quiet_NaN();
    info.solve_time_ms = ms_since(t0);
    return res;
  }
  if (settings_.warm_start && have_prev_) {
    yh_.resize(m);
    for (int i = 0; i < m; ++i) yh_(i) = s_ * Einv_(i) * dual_prev_(i / 3, i % 3);
    xh_.resize(nfd);
    for (int j = 0; j < nf_; ++j)
      xh_.segment<3>(3 * j) = (V_prev_.row(free_(j)) - U_.row(free_(j))).transpose();
    xh_ = Dinv_.cwiseProduct(xh_);
  } else {
    xh_.setZero(nfd);
    yh_.setZero(m);
  }
  zh_ = Ah_ * xh_;

  const double alpha = settings_.alpha;
  Eigen::VectorXd rhs(nfd), xt(nfd), zt(m), zr(m), v(m), zn(m), Ax(m), ATy(nfd), tmp(m);
  Eigen::VectorXd ya(m), yb(m), ybest(m), dy(m), atya(nfd), atyb(nfd), atybest(nfd), da(nfd);
  bool have_best = false;
  // rho from the data: the ratio of the dual scale (the weights) to the primal scale, the
  // nodal forces of the solution. The previous frame's solution is the best predictor of this
  // frame's (noise-only frames leave forces ~1e-3 of the raw nodal forces and want a large
  // rho; contacts leave large forces and want a small one). Refactor only when it moves by
  // more than the tolerance.
  const double fb = std::sqrt(bh_.squaredNorm() / n_);
  {
    const double fs =
        force_scale_ > 0 ? std::max(force_scale_, kMinForceRatio * fb) : kFirstForceRatio * fb;
    if (fs > 0) {
      const double target = settings_.rho * wh_.mean() / fs;
      const double ratio = target / rho_of(rho_idx_);
      if (!rho_set_ || ratio > settings_.adaptive_rho_tolerance ||
          ratio < 1.0 / settings_.adaptive_rho_tolerance) {
        rho_idx_ = static_cast<int>(std::lround(kRhoGridPerDecade * std::log10(target)));
        rho_set_ = true;
      }
    }
  }
  const BlockLDLT* ldlt = &factor(rho_idx_, &info.factorizations);
  double rho = rho_of(rho_idx_);
  info.status = SolverStatus::max_iter_reached;
  int k = 0;
  double pobj = 0, gap = 0, rp = 0, rd = 0;
  const int mem = settings_.anderson_memory;
  Anderson aa(std::max(mem, 1), 2 * m);
  Eigen::VectorXd u(2 * m), g(2 * m);
  for (k = 1; k <= settings_.max_iter; ++k) {
    if (mem > 0) {
      u.head(m) = zh_;
      u.tail(m) = yh_ / rho;
    }
    tmp.noalias() = rho * zh_ - yh_;
    Ab_.multiply_transposed(tmp, rhs);
    rhs += settings_.sigma * xh_;
    ldlt->solve(rhs, xt);
    Ab_.multiply(xt, zt);
    xh_ = alpha * xt + (1 - alpha) * xh_;
    zr = alpha * zt + (1 - alpha) * zh_;
    v = zr + yh_ / rho;
    prox(v, rho, zn);
    yh_ += rho * (zr - zn);
    zh_.swap(zn);
    if (mem > 0) {
      g.head(m) = zh_;
      g.tail(m) = yh_ / rho;
      aa.step(u, g);
      zh_ = g.head(m);
      yh_ = rho * g.tail(m);
    }

    const bool last = k == settings_.max_iter;
    if (k % settings_.check_interval != 0 && !last) continue;
    Ab_.multiply(xh_, Ax);
    Ab_.multiply_transposed(yh_, ATy);
    // Objective at x (unscaled, unitless).
    pobj = c_ * D_.cwiseProduct(xh_).squaredNorm() + rim_const_;
    for (int i = 0; i < n_; ++i)
      pobj += w_(i) * (Ax.segment<3>(3 * i) + bh_.segment<3>(3 * i)).norm() * Einv_(3 * i);
    // Dual bound d(y) = y.b - |A^T y|^2_{P^-1} / 2 at a feasible y (||y_i|| <= w_i), improved
    // cheaply: (a) the ADMM multiplier projected on its balls; (b) the same with the nodes where
    // x leaves a force replaced by w_i F_i / ||F_i|| (the multiplier x asks for); the best point
    // on the segment a-b, then on the segment to the best multiplier of the previous check, then
    // the best scaling along the ray. All these stay feasible and need two products with A^T.
    for (int cand = 0; cand < 2; ++cand) {
      Eigen::VectorXd& y = cand == 0 ? ya : yb;
      y = yh_;
      for (int i = 0; i < n_; ++i) {
        if (cand == 1) {
          const Eigen::Vector3d f = Ax.segment<3>(3 * i) + bh_.segment<3>(3 * i);
          const double fn = f.norm();
          if (fn > 1e-9 * wh_(i) / rho) {
            y.segment<3>(3 * i) = wh_(i) / fn * f;
            continue;
          }
        }
        const double nr = y.segment<3>(3 * i).norm();
        if (nr > wh_(i)) y.segment<3>(3 * i) *= wh_(i) / nr;
      }
      Ab_.multiply_transposed(y, cand == 0 ? atya : atyb);
    }
    auto segment_max = [&](Eigen::VectorXd& y1, Eigen::VectorXd& a1, const Eigen::VectorXd& y2,
                           const Eigen::VectorXd& a2) {
      dy = y2 - y1;
      da = a2 - a1;
      const double dd = da.cwiseAbs2().cwiseQuotient(Pd_).sum();
      if (!(dd > 0)) return;
      const double t =
          std::clamp((dy.dot(bh_) - a1.cwiseProduct(da).cwiseQuotient(Pd_).sum()) / dd, 0.0, 1.0);
      y1 += t * dy;
      a1 += t * da;
    };
    segment_max(ya, atya, yb, atyb);
    if (have_best) segment_max(ya, atya, ybest, atybest);
    {
      const double lin = ya.dot(bh_);
      const double quad = atya.cwiseAbs2().cwiseQuotient(Pd_).sum();
      double tmax = std::numeric_limits<double>::infinity();
      for (int i = 0; i < n_; ++i) {
        const double nr = ya.segment<3>(3 * i).norm();
        if (nr > 0) tmax = std::min(tmax, wh_(i) / nr);
      }
      double t = quad > 0 ? lin / quad : (lin > 0 ? tmax : 0.0);
      t = std::clamp(t, 0.0, std::isfinite(tmax) ? tmax : 1.0);
      ybest = t * ya;
      atybest = t * atya;
      have_best = true;
    }
    const double dual_h = ybest.dot(bh_) - 0.5 * atybest.cwiseAbs2().cwiseQuotient(Pd_).sum();
    const double dobj = dual_h / s_ + rim_const_;
    gap = std::max(pobj - dobj, 0.0);
    rp = (Ax - zh_).cwiseProduct(Einv_).lpNorm<Eigen::Infinity>();
    rd = (Pd_.cwiseProduct(xh_) + ATy).cwiseProduct(Dinv_).lpNorm<Eigen::Infinity>() / s_;
    if (!std::isfinite(pobj) || !xh_.allFinite()) {
      info.status = SolverStatus::non_finite_input;
      break;
    }
    if (gap <= settings_.eps_abs + settings_.eps_rel * std::abs(pobj)) {
      info.status = SolverStatus::solved;
      break;
    }
    if (settings_.time_limit > 0 && ms_since(t0) > 1e3 * settings_.time_limit) {
      info.status = SolverStatus::time_limit_reached;
      break;
    }
    if (settings_.adaptive_rho && k % settings_.adaptive_rho_interval < settings_.check_interval) {
      // The same rule as between frames, on the current iterate: a frame unlike the last one
      // (a contact made or released) gets its rho within the solve.
      const double fs = std::max(std::sqrt((Ax + bh_).squaredNorm() / n_), kMinForceRatio * fb);
      const double ratio = settings_.rho * wh_.mean() / fs / rho;
      if (fs > 0 && (ratio > settings_.adaptive_rho_tolerance ||
                     ratio < 1.0 / settings_.adaptive_rho_tolerance)) {
        rho_idx_ = static_cast<int>(std::lround(kRhoGridPerDecade * std::log10(ratio * rho)));
        rho_idx_ = std::clamp(rho_idx_, -80, 80);
        ldlt = &factor(rho_idx_, &info.factorizations);
        rho = rho_of(rho_idx_);
        aa.reset();
      }
    }
  }
  info.setup_time_ms = factor_ms_;
  info.iterations = std::min(k, settings_.max_iter);
  info.objective = pobj;
  info.duality_gap = gap;
  info.primal_residual = rp;
  info.dual_residual = rd;
  info.rho = rho;
  const Eigen::VectorXd x = D_.cwiseProduct(xh_);
  for (int i = 0; i < n_; ++i)
    if (is_rim_(i)) res.dU.row(i) = -U_.row(i);
  for (int j = 0; j < nf_; ++j) res.dU.row(free_(j)) = x.segment<3>(3 * j).transpose();
  for (int i = 0; i < m; ++i) res.dual(i / 3, i % 3) = yh_(i) * E_(i) / s_;
  if (info.status != SolverStatus::non_finite_input) {
    Ab_.multiply(xh_, Ax);
    force_scale_ = std::sqrt((Ax + bh_).squaredNorm() / n_);
    V_prev_ = U_ + res.dU;
    dual_prev_ = res.dual;
    have_prev_ = true;
    fresh_ = info.status == SolverStatus::solved;
  } else {
    have_prev_ = false;
  }
  info.solve_time_ms = ms_since(t0);
  if (fresh_) last_ = res;
  return res;
}

}  // namespace bubble
