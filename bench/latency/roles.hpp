// The roles of lcmx_bench_latency's methods (children of the orchestrator, bench/harness/
// pingpong.hpp's protocol); each returns the child's exit code. lcmx_bench_udp reuses the
// liblcm pair (liblcm.cpp), and bench/python/bench_python.py the lcmx ones.
#pragma once

#include <cstddef>
#include <cstdint>

#include "harness/pingpong.hpp"
#include "lcmx_examples/bench_t.hpp"

namespace lcmxbench {

int run_floor_sub(const RoleConfig& cfg);   // floor.cpp: the minimal futex shm ping-pong
int run_floor_pub(const RoleConfig& cfg);
int run_liblcm_sub(const RoleConfig& cfg);  // liblcm.cpp: stock liblcm udpm
int run_liblcm_pub(const RoleConfig& cfg);
int run_lcmx_sub(const RoleConfig& cfg, bool loan);  // lcmx.cpp: typed shm, or loan + raw zero-copy
int run_lcmx_pub(const RoleConfig& cfg, bool loan);
int run_lcmx_intra(const RoleConfig& cfg);  // both nodes in one process

// A bench_t of `size` payload bytes, filled with the same pattern by every publisher role.
inline void fill_bench(lcmx_examples::bench_t& msg, std::size_t size) {
  msg.size = static_cast<std::int32_t>(size);
  msg.data.resize(size);
  for (std::size_t i = 0; i < size; ++i) msg.data[i] = static_cast<std::uint8_t>(i * 31u);
}

}  // namespace lcmxbench
