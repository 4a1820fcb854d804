// Dense Cholesky factorization A = L L^T through LAPACK (OpenBLAS): the refit's support
// system H_SS, up to about 500 rows, factored once per frame, and the inverse of
// K_ff K_ff^T that the refit forms once per model.
//
// OpenBLAS picks its kernels for the CPU at run time (AVX2 and FMA where the machine has them),
// while Eigen's own kernels are fixed when the portable wheel is compiled (SSE2): at 498 rows
// dpotrf takes 1.7 ms against Eigen's 5.8 ms in one run on this machine class
// (docs/evaluation.md, "The refit's dense algebra through OpenBLAS").
#pragma once

#include <Eigen/Core>

namespace bubble {

// One thread for every BLAS / LAPACK call of this process: the estimator's stages already run
// in parallel, and a threaded factorization of a few hundred rows competes with them for the
// cores. Idempotent; the module calls it once at import.
void use_single_threaded_blas();

// A^{-1} for a symmetric positive definite A (its lower triangle is read), from its Cholesky
// factor (dpotrf, then dpotri). Throws InputError when A is not positive definite.
Eigen::MatrixXd spd_inverse(Eigen::MatrixXd A);

class DenseCholesky {
 public:
  // Factors A (symmetric positive definite; only its lower triangle is read). Throws
  // InputError when A is not square or not positive definite.
  void compute(Eigen::MatrixXd A);
  // x = A^{-1} b.
  Eigen::VectorXd solve(const Eigen::VectorXd& b) const;

 private:
  Eigen::MatrixXd L_;  // lower triangle: the factor (the strict upper triangle is unused)
};

}  // namespace bubble
