// Exact floating-point expansion arithmetic (Shewchuk-style), host+device.
//
// An expansion is a sum of non-overlapping doubles stored in increasing
// magnitude; its value is exact. Only the operations the predicates need are
// here: exact sum/difference/product of two doubles, growing an expansion by a
// double, scaling by a double, summing and multiplying expansions, and sign.
// Every routine eliminates zero components, so lengths stay small in practice.
//
// Exactness requires no overflow and no underflow of the partial products;
// `kMaxAbsCoordinate` / `kMinAbsCoordinate` in predicates.h bound the inputs
// so that this holds.
#ifndef KINETRI_CORE_EXPANSION_H_
#define KINETRI_CORE_EXPANSION_H_

#include <cmath>

#include "core/hd.h"

namespace kinetri::core::exact {

// x + y == a + b exactly, with x = fl(a + b).
KINETRI_HD inline void TwoSum(double a, double b, double& x, double& y) {
  x = a + b;
  const double bv = x - a;
  const double av = x - bv;
  const double br = b - bv;
  const double ar = a - av;
  y = ar + br;
}

// x + y == a - b exactly, with x = fl(a - b).
KINETRI_HD inline void TwoDiff(double a, double b, double& x, double& y) {
  x = a - b;
  const double bv = a - x;
  const double av = x + bv;
  const double br = bv - b;
  const double ar = a - av;
  y = ar + br;
}

// x + y == a * b exactly, with x = fl(a * b); the tail comes from one fused
// multiply-add, which is exact.
KINETRI_HD inline void TwoProduct(double a, double b, double& x, double& y) {
  x = a * b;
  y = std::fma(a, b, -x);
}

// Fixed-capacity expansion; N is the worst-case component count.
template <int N>
struct Expansion {
  double c[N];
  int n = 0;
};

// h = e + b. Capacity of h must be >= e.n + 1.
template <int N, int M>
KINETRI_HD void Grow(const Expansion<N>& e, double b, Expansion<M>& h) {
  double q = b;
  int k = 0;
  for (int i = 0; i < e.n; ++i) {
    double sum, tail;
    TwoSum(q, e.c[i], sum, tail);
    q = sum;
    if (tail != 0.0) h.c[k++] = tail;
  }
  if (q != 0.0 || k == 0) h.c[k++] = q;
  h.n = k;
}

// h = e (the first e.n components).
template <int N, int M>
KINETRI_HD void Assign(const Expansion<N>& e, Expansion<M>& h) {
  for (int i = 0; i < e.n; ++i) h.c[i] = e.c[i];
  h.n = e.n;
}

// h = e + f (repeated Grow; output non-overlapping). h must not be e or f.
// The Grow steps alternate between h and one scratch expansion, the last
// one into h, so no step copies a whole expansion.
template <int N, int M, int K>
KINETRI_HD void Sum(const Expansion<N>& e, const Expansion<M>& f,
                    Expansion<K>& h) {
  static_assert(K >= N + M, "Sum: output capacity too small");
  if (f.n == 0) {
    Assign(e, h);
    return;
  }
  Expansion<K> scratch;
  Expansion<K>* dst = f.n % 2 == 1 ? &h : &scratch;
  Grow(e, f.c[0], *dst);
  for (int j = 1; j < f.n; ++j) {
    Expansion<K>* src = dst;
    dst = src == &h ? &scratch : &h;
    Grow(*src, f.c[j], *dst);
  }
}

// h = -e.
template <int N>
KINETRI_HD void Negate(Expansion<N>& e) {
  for (int i = 0; i < e.n; ++i) e.c[i] = -e.c[i];
}

// h = e * b.
template <int N, int M>
KINETRI_HD void Scale(const Expansion<N>& e, double b, Expansion<M>& h) {
  static_assert(M >= 2 * N, "Scale: output capacity too small");
  int k = 0;
  if (e.n == 0 || b == 0.0) {
    h.c[0] = 0.0;
    h.n = 1;
    return;
  }
  double q, tail;
  TwoProduct(e.c[0], b, q, tail);
  if (tail != 0.0) h.c[k++] = tail;
  for (int i = 1; i < e.n; ++i) {
    double p1, p0;
    TwoProduct(e.c[i], b, p1, p0);
    double s, t;
    TwoSum(q, p0, s, t);
    if (t != 0.0) h.c[k++] = t;
    TwoSum(p1, s, q, t);
    if (t != 0.0) h.c[k++] = t;
  }
  if (q != 0.0 || k == 0) h.c[k++] = q;
  h.n = k;
}

// h = e * f. h must not be e or f. The accumulator alternates between h
// and one scratch expansion (no step copies a whole expansion).
template <int N, int M, int K>
KINETRI_HD void Multiply(const Expansion<N>& e, const Expansion<M>& f,
                         Expansion<K>& h) {
  static_assert(K >= 2 * N * M, "Multiply: output capacity too small");
  Expansion<K> scratch;
  Expansion<K>* acc = &h;
  Expansion<K>* next = &scratch;
  acc->c[0] = 0.0;
  acc->n = 1;
  for (int j = 0; j < f.n; ++j) {
    Expansion<2 * N> part;
    Scale(e, f.c[j], part);
    for (int i = 0; i < part.n; ++i) {
      Grow(*acc, part.c[i], *next);
      Expansion<K>* done = acc;
      acc = next;
      next = done;
    }
  }
  if (acc != &h) Assign(*acc, h);
}

// Exact a - b as a two-component expansion.
KINETRI_HD inline Expansion<2> Diff(double a, double b) {
  Expansion<2> e;
  double x, y;
  TwoDiff(a, b, x, y);
  e.n = 0;
  if (y != 0.0) e.c[e.n++] = y;
  e.c[e.n++] = x;
  return e;
}

// Sign of the expansion's value: its largest component decides.
template <int N>
KINETRI_HD int Sign(const Expansion<N>& e) {
  for (int i = e.n - 1; i >= 0; --i) {
    if (e.c[i] > 0.0) return 1;
    if (e.c[i] < 0.0) return -1;
  }
  return 0;
}

}  // namespace kinetri::core::exact

#endif  // KINETRI_CORE_EXPANSION_H_
