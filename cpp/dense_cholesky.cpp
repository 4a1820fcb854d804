#include "dense_cholesky.h"

#include <string>

#include "errors.h"

extern "C" {
// LAPACK / OpenBLAS (Fortran calling convention: every argument by pointer).
void dpotrf_(const char* uplo, const int* n, double* a, const int* lda, int* info);
void dpotri_(const char* uplo, const int* n, double* a, const int* lda, int* info);
void openblas_set_num_threads(int n);
}

namespace bubble {

namespace {
const char kLower = 'L';

// Overwrites the lower triangle of the n x n matrix at a with its Cholesky factor.
void factor_lower(Eigen::MatrixXd& a) {
  const int n = static_cast<int>(a.rows());
  int info = 0;
  dpotrf_(&kLower, &n, a.data(), &n, &info);
  require(info == 0, "dense Cholesky: matrix not positive definite (LAPACK info " +
                         std::to_string(info) + ")");
}
}  // namespace

void use_single_threaded_blas() { openblas_set_num_threads(1); }

Eigen::MatrixXd spd_inverse(Eigen::MatrixXd A) {
  require(A.rows() == A.cols(), "spd_inverse: matrix must be square");
  const int n = static_cast<int>(A.rows());
  if (n == 0) return A;
  factor_lower(A);
  int info = 0;
  dpotri_(&kLower, &n, A.data(), &n, &info);
  require(info == 0, "spd_inverse: singular factor (LAPACK info " + std::to_string(info) + ")");
  A.triangularView<Eigen::StrictlyUpper>() = A.transpose();
  return A;
}

void DenseCholesky::compute(Eigen::MatrixXd A) {
  require(A.rows() == A.cols(), "DenseCholesky: matrix must be square");
  L_ = std::move(A);
  if (L_.rows() > 0) factor_lower(L_);
}

Eigen::VectorXd DenseCholesky::solve(const Eigen::VectorXd& b) const {
  Eigen::VectorXd x = L_.triangularView<Eigen::Lower>().solve(b);
  L_.triangularView<Eigen::Lower>().transpose().solveInPlace(x);
  return x;
}

}  // namespace bubble
