// Warm-started ADMM for the regularised force estimate (docs/method.md, "How the solver works").
//
//   minimise  sum_i w_i || F_ext(U + dU, dp)_i ||  +  (k_u / N) sum_i || dU_i ||^2
//   s.t.      (U + dU)_i = 0 on the rim,   w_i = k_f |rim| / N on the rim, k_f elsewhere.
//
// The rim constraint is exact: rim dofs are eliminated, the unknown is x = dU on free nodes.
// With F = A x + b (A = the free columns of K, b = A U_free - dp a n) the problem is
//   minimise  c ||x||^2 + sum_i w_i ||(A x + b)_i||,   c = k_u / N,
// split OSQP-style as z = A x: the x-update is a sparse solve with (P + sigma I + rho A^T A)
// (factored once per rho), the z-update a block soft-threshold, plus over-relaxation.
// Scaling: the cost is multiplied by s = 1 / (2 c) (the quadratic becomes ||x||^2 / 2 in
// metres; optional per-node Ruiz equilibration on top). rho is set from the data, not fixed:
// rho = settings.rho * mean(scaled weights) / force scale, the force scale being the rms
// nodal force of the previous frame's solution (the dual scale over the primal scale; on the
// first frame, 3e-3 of the rms nodal force at dU = 0). Untouched frames leave tiny forces and
// get a large rho, contacts a small one; measured on rendered frames this halves the
// iterations against a rule on the raw forces. The rule is unit-free, so the ADMM iterates
// are identical under a change of units (m <-> mm, N <-> mN). With adaptive_rho the same
// rule is re-applied inside a solve every adaptive_rho_interval iterations (a contact made or
// released within one frame). rho lives on a grid of quarter decades; each factorization is
// cached, so returning to a rho is free, a new rho costs only the numeric factorization (the
// ordering and symbolic analysis are shared, block_ldlt.h), and rho is re-set only when the rule
// moves it by more than adaptive_rho_tolerance. Anderson acceleration of the fixed-point map
// of v = z + y / rho (the Douglas-Rachford variable: z = prox(v), y / rho = v - prox(v)).
//
// Termination uses the duality gap: every dual iterate is dual feasible (||y_i|| <= w_i), so
// objective(x) - dual(y) bounds the suboptimality of the returned x. "solved" means
// gap <= eps_abs + eps_rel * objective, confirmed with A x recomputed. A check is cheap: A x
// is carried by the over-relaxation, the dual bound takes two products with A^T. The next check is
// placed where the gap's rate since the last one says it reaches the tolerance, check_interval
// iterations at most.
#pragma once

#include <Eigen/Core>
#include <Eigen/Dense>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "block_ldlt.h"
#include "block_matrix.h"
#include "membrane.h"

namespace bubble {

struct SolverSettings {
  double rho = 0.5;                    // multiplier of the data-driven rho (see above)
  double sigma = 1e-6;                 // proximal regularisation of the x-update
  double alpha = 1.6;                  // over-relaxation in (0, 2)
  bool adaptive_rho = true;            // re-set rho inside a solve from the iterate's forces
  double adaptive_rho_tolerance = 2.;  // change rho only when it moves by more than this factor
  int adaptive_rho_interval = 25;      // iterations between rho updates
  double eps_abs = 1e-5;               // absolute duality-gap tolerance (objective is unitless)
  double eps_rel = 8e-4;               // relative duality-gap tolerance
  int max_iter = 4000;
  int check_interval = 5;   // most iterations between termination checks (see above)
  double time_limit = 0.0;  // seconds per warm-started solve, 0 = none (a cold one runs on)
  int scaling_iter = 0;     // Ruiz equilibration passes, 0 = no scaling
  bool warm_start = true;   // start each solve from the previous solution
  int anderson_memory = 5;  // Anderson acceleration memory (0 = off)
  void validate() const;    // throws InputError
};

enum class SolverStatus { solved, max_iter_reached, time_limit_reached, non_finite_input };
std::string to_string(SolverStatus s);

struct SolverInfo {
  SolverStatus status = SolverStatus::max_iter_reached;
  int iterations = 0;
  double primal_residual = 0;  // ||A x - z||_inf in newtons
  double dual_residual = 0;    // ||P x + A^T y||_inf (objective per metre)
  double objective = 0;        // objective at the returned dU (unitless)
  double duality_gap = 0;      // objective - best dual bound (unitless, >= 0)
  double rho = 0;              // rho in use at the end (scaled problem)
  int factorizations = 0;      // factorizations computed during this solve
  double setup_time_ms = 0;    // factorization time spent inside this solve (0 when cached)
  double solve_time_ms = 0;
};

struct SolverResult {
  RowMatrixX3d dU;    // N x 3 correction (m); rim rows are -U_rim
  RowMatrixX3d dual;  // N x 3 multipliers of F_ext, ||dual_i|| <= w_i: the certificate's dual point
  SolverInfo info;
};

class GroupLassoSolver {
 public:
  // K: 3N x 3N stiffness; area_normals: N x 3 (a_i n_i); boundary: rim node indices.
  GroupLassoSolver(const SparseMatrixd& K, const Eigen::Ref<const RowMatrixX3d>& area_normals,
                   const Eigen::Ref<const Eigen::VectorXi>& boundary, double k_f, double k_u,
                   const SolverSettings& settings = SolverSettings());

  // Changes the weights; rescales and refactors (cheap but not per-frame).
  void set_weights(double k_f, double k_u);
  // Changes settings; refactors only if rho or scaling changed.
  void set_settings(const SolverSettings& settings);
  const SolverSettings& settings() const { return settings_; }

  // New frame data (no refactorisation). Throws InputError (state untouched) on bad input.
  void update(const Eigen::Ref<const RowMatrixX3d>& U, double dp);
  // Start the next solve from corrected displacements V = U + dU (N x 3) and multipliers.
  void warm_start(const Eigen::Ref<const RowMatrixX3d>& V,
                  const Eigen::Ref<const RowMatrixX3d>& dual);
  // Forget the previous solution and force scale: the next solve starts as the first one
  // did (dU = 0, dual = 0, rho from its own data).
  void cold_start();
  SolverResult solve();

  int n_nodes() const { return n_; }
  double setup_time_ms() const { return setup_ms_; }

 private:
  void setup();  // scaling + A^T A + first factorization
  const BlockLDLT& factor(int rho_index, int* count);
  double rho_of(int idx) const;

  // The steps of solve(), in the order of one ADMM iteration; SolveState (group_lasso.cpp)
  // holds what lives for one solve: rho and its factor, scratch vectors, Anderson memory.
  struct SolveState;
  struct DualPoint;
  SolverResult repeat_last(double elapsed_ms) const;
  void start_iterates();
  // rho: one rule (weights over the force scale), applied per frame and inside a solve.
  double rho_target(double force_scale) const;
  bool rho_should_move(double ratio) const;
  void set_frame_rho(double raw_force_scale);
  void use_rho(SolveState& st, int* factorizations);
  void adapt_rho(SolveState& st, int* factorizations);
  static double relative_gap(const SolveState& st);  // gap / |objective|
  // One iteration.
  void admm_iteration(SolveState& st);
  void x_update(SolveState& st) const;
  void over_relax(SolveState& st);
  void prox(const Eigen::VectorXd& v, double inv_rho, Eigen::VectorXd& out) const;
  void z_update(SolveState& st) const;  // block soft-threshold
  void dual_update(SolveState& st);
  void anderson_step(SolveState& st);
  // Every check_interval iterations: residuals and the duality-gap certificate.
  void measure(SolveState& st) const;
  void exact_measure(SolveState& st) const;
  void schedule_check(SolveState& st, int k) const;
  double dual_residual() const;
  double objective(const Eigen::VectorXd& Ax) const;
  double dual_bound(SolveState& st) const;
  void projected_multiplier(DualPoint& p) const;
  void stationary_multiplier(const SolveState& st, DualPoint& p) const;
  void maximize_on_segment(DualPoint& p1, const DualPoint& p2, SolveState& st) const;
  void best_scaling(const DualPoint& p, DualPoint& out) const;
  double dual_value(const DualPoint& p) const;
  std::optional<SolverStatus> termination(const SolveState& st) const;
  // After the loop.
  void write_result(const SolveState& st, int iterations, SolverResult& res) const;
  void remember_solution(SolveState& st, const SolverResult& res);

  int n_ = 0, nf_ = 0;
  Eigen::VectorXi free_;    // free node ids
  Eigen::VectorXi is_rim_;  // 1 on rim
  SparseMatrixd A_;         // 3N x 3Nf, unscaled
  RowMatrixX3d an_;         // a n
  Eigen::VectorXd w_;       // N weights
  double k_f_ = 0, k_u_ = 0, c_ = 0;
  SolverSettings settings_;

  // Scaling: x = D xh, zh = E z, cost multiplied by s.
  Eigen::VectorXd D_, E_, Dinv_, Einv_;  // per dof / per row (expanded)
  Eigen::VectorXd wh_;                   // s w_i / E_i per node
  double s_ = 1;
  SparseMatrixd Ah_, AhT_, AtA_;
  // Ah_ and its transpose in 3 x 3 blocks, for the per-iteration products (both by rows:
  // a gather per row is faster than the scatter of a transposed product).
  BlockMatrix3 Ab_, AbT_;
  Eigen::VectorXd Pd_;  // diagonal of the scaled P = 2 s c D^2
  std::map<int, std::unique_ptr<BlockLDLT>> factors_;
  int rho_idx_ = 0;
  bool rho_set_ = false;
  double force_scale_ = 0;  // rms nodal force of the last solution (scaled), 0 = none yet

  // Frame data.
  bool have_data_ = false;
  RowMatrixX3d U_;
  double dp_ = 0;
  Eigen::VectorXd bh_;  // scaled b
  double rim_const_ = 0;

  // Iterates (scaled).
  bool have_prev_ = false;
  RowMatrixX3d V_prev_, dual_prev_;
  // The last result, returned again when solve() sees exactly the same data (determinism).
  bool fresh_ = false;
  SolverResult last_;
  Eigen::VectorXd xh_, zh_, yh_;
  double setup_ms_ = 0;
  double factor_ms_ = 0;
};

}  // namespace bubble
