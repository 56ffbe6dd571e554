// The bench_t messages of one channel in an LCM log written by `lcmx record` (tests of the
// start-up race, one host and across hosts).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "lcmx/log/eventlog.hpp"
#include "lcmx_examples/bench_t.hpp"

namespace lcmx::it {

// Their seq fields, in log order; what can be read so far (a partly written last event, or no
// file yet, ends the list).
inline std::vector<std::int64_t> logged_bench_seqs(const std::string& path, const std::string& channel) {
  std::vector<std::int64_t> out;
  try {
    auto r = lcmx::eventlog::Reader::open(path);
    lcmx::eventlog::Event e;
    while (r.next(e)) {
      if (e.channel != channel) continue;
      lcmx_examples::bench_t m;
      if (m.decode(e.data.data(), 0, static_cast<int>(e.data.size())) > 0) out.push_back(m.seq);
    }
  } catch (const lcmx::eventlog::Error&) {
  }
  return out;
}

}  // namespace lcmx::it
