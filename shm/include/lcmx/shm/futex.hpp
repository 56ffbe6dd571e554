// Futex helpers for words in shared memory (process-shared futexes).
// Threads: all functions are thread-safe. Errors: Error(system) on unexpected errno.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <span>

#include "lcmx/shm/segment.hpp"

namespace lcmx::shm {

// Wakes every thread (any process) waiting on `word`. Returns the number woken.
int futex_wake_all(const std::atomic<std::uint32_t>* word) noexcept;
// Same for a word in process-private memory waited on with WaitToken::process_private (a
// private wake does not reach shared waiters and vice versa).
int futex_wake_all_private(const std::atomic<std::uint32_t>* word) noexcept;

enum class WaitResult { woken, timeout };

// Sleeps until any token's word differs from its expected value, a wake-up on one of them,
// or the timeout (negative = forever). May return woken spuriously. Uses futex_waitv (Linux
// >= 5.16) for several tokens; with one token, plain FUTEX_WAIT. Any number of tokens: above
// the 128 futex_waitv takes, the kernel sleeps on the first 128 and the others' words are
// compared every 1 ms (a change there is seen at most 1 ms late, never lost; costs a little
// CPU when idle). On kernels without futex_waitv and several tokens, waits on the first token
// and returns at least every 1 ms (same costs).
// Throws Error(invalid_argument) for no token or a null word, Error(system) on an unexpected
// errno.
WaitResult wait_any(std::span<const WaitToken> tokens, std::chrono::nanoseconds timeout);

bool futex_waitv_supported() noexcept;

}  // namespace lcmx::shm
