// The atomics the device executor needs (claims, last-writer marks, the
// queries' stop word), relaxed, callable from host and device code. libcu++'s
// cuda::atomic_ref where it exists (the CUDA toolkit's CCCL, also used by
// the emulated backend on CPU threads); GCC's builtins on hosts without it.
#ifndef KINETRI_CORE_DEVICE_ATOMIC_H_
#define KINETRI_CORE_DEVICE_ATOMIC_H_

#include <cstdint>

#include "core/hd.h"

#if __has_include(<cuda/atomic>)
#include <cuda/atomic>
#define KINETRI_HAS_LIBCUDACXX 1
#endif

namespace kinetri::core::device {

KINETRI_HD inline void ClaimMin(uint32_t* slot, uint32_t value) {
#ifdef KINETRI_HAS_LIBCUDACXX
  cuda::atomic_ref<uint32_t, cuda::thread_scope_device> ref(*slot);
  ref.fetch_min(value, cuda::std::memory_order_relaxed);
#else
  uint32_t cur = __atomic_load_n(slot, __ATOMIC_RELAXED);
  while (value < cur &&
         !__atomic_compare_exchange_n(slot, &cur, value, /*weak=*/true,
                                      __ATOMIC_RELAXED, __ATOMIC_RELAXED)) {
  }
#endif
}

// *slot = max(*slot, value), relaxed.
KINETRI_HD inline void ClaimMax(uint32_t* slot, uint32_t value) {
#ifdef KINETRI_HAS_LIBCUDACXX
  cuda::atomic_ref<uint32_t, cuda::thread_scope_device> ref(*slot);
  ref.fetch_max(value, cuda::std::memory_order_relaxed);
#else
  uint32_t cur = __atomic_load_n(slot, __ATOMIC_RELAXED);
  while (value > cur &&
         !__atomic_compare_exchange_n(slot, &cur, value, /*weak=*/true,
                                      __ATOMIC_RELAXED, __ATOMIC_RELAXED)) {
  }
#endif
}

// *slot = value for a slot other threads may write the same value to;
// kSystem: a word the host reads or writes while kernels run (pinned host
// memory on a GPU), with system scope.
KINETRI_HD inline void AddRelaxed(uint32_t* slot, uint32_t value) {
#ifdef KINETRI_HAS_LIBCUDACXX
  cuda::atomic_ref<uint32_t, cuda::thread_scope_device> ref(*slot);
  ref.fetch_add(value, cuda::std::memory_order_relaxed);
#else
  __atomic_fetch_add(slot, value, __ATOMIC_RELAXED);
#endif
}

// Returns the old *slot and adds `value`, relaxed (an append's position).
KINETRI_HD inline uint32_t FetchAdd(uint32_t* slot, uint32_t value) {
#ifdef KINETRI_HAS_LIBCUDACXX
  cuda::atomic_ref<uint32_t, cuda::thread_scope_device> ref(*slot);
  return ref.fetch_add(value, cuda::std::memory_order_relaxed);
#else
  return __atomic_fetch_add(slot, value, __ATOMIC_RELAXED);
#endif
}

// Returns the old *slot and sets the bits of `bits`, relaxed (a set's
// "first to insert" test).
KINETRI_HD inline uint32_t FetchOr(uint32_t* slot, uint32_t bits) {
#ifdef KINETRI_HAS_LIBCUDACXX
  cuda::atomic_ref<uint32_t, cuda::thread_scope_device> ref(*slot);
  return ref.fetch_or(bits, cuda::std::memory_order_relaxed);
#else
  return __atomic_fetch_or(slot, bits, __ATOMIC_RELAXED);
#endif
}

// Clears the bits of `bits` in *slot, relaxed.
KINETRI_HD inline void ClearBits(uint32_t* slot, uint32_t bits) {
#ifdef KINETRI_HAS_LIBCUDACXX
  cuda::atomic_ref<uint32_t, cuda::thread_scope_device> ref(*slot);
  ref.fetch_and(~bits, cuda::std::memory_order_relaxed);
#else
  __atomic_fetch_and(slot, ~bits, __ATOMIC_RELAXED);
#endif
}

template <bool kSystem = false>
KINETRI_HD inline void StoreRelaxed(uint32_t* slot, uint32_t value) {
#ifdef KINETRI_HAS_LIBCUDACXX
  cuda::atomic_ref<uint32_t, kSystem ? cuda::thread_scope_system
                                     : cuda::thread_scope_device>
      ref(*slot);
  ref.store(value, cuda::std::memory_order_relaxed);
#else
  __atomic_store_n(slot, value, __ATOMIC_RELAXED);
#endif
}

KINETRI_HD inline void StoreSystem(uint32_t* word, uint32_t value) {
  StoreRelaxed</*kSystem=*/true>(word, value);
}

// *word, read with system scope, relaxed (see StoreRelaxed).
KINETRI_HD inline uint32_t LoadSystem(const uint32_t* word) {
#ifdef KINETRI_HAS_LIBCUDACXX
  cuda::atomic_ref<uint32_t, cuda::thread_scope_system> ref(
      *const_cast<uint32_t*>(word));
  return ref.load(cuda::std::memory_order_relaxed);
#else
  return __atomic_load_n(word, __ATOMIC_RELAXED);
#endif
}

}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_ATOMIC_H_
