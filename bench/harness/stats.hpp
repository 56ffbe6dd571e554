// Percentile statistics of a benchmark's samples (bench/harness). Every percentile is
// nearest-rank: p-th = the ceil(p * n)-th smallest sample (p50 of 1..4 is 2, p99 of 100
// samples the 99th).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

namespace lcmxbench {

struct Stats {
  std::size_t n = 0;
  double mean = 0, p50 = 0, p99 = 0, min = 0, max = 0;  // in the samples' unit; 0 when n == 0
};

// The nearest-rank `q`-quantile (0 < q <= 1) of sorted samples; 0 if there are none.
double nearest_rank(const std::vector<double>& sorted, double q);
// Stats of samples in any unit.
Stats stats_of(std::vector<double> samples);
// Stats in µs of samples in ns.
Stats stats_of_ns(const std::vector<std::int64_t>& ns);
// The median (the mean of the middle two for an even count); 0 if there are none.
double median(std::vector<double> v);

}  // namespace lcmxbench
