// lcmx_bench_fingerprints: prints, as one JSON object, the 8-byte lcm fingerprint (getHash(), the
// first 8 bytes of every encoded message, big-endian) of each type that travels on LCMX_BEACON,
// as 16 hex digits: {"beacon_t": "…", "records_t": "…", ...}. listen.py classifies the datagrams
// it hears by them (run.py passes them). A type this build does not have (marker_t before the
// lcmtypes that define it are merged) is null: listen.py then counts nothing as that type.
#include <cinttypes>
#include <cstdint>
#include <cstdio>

#include "lcmx_msgs/beacon_t.hpp"
#include "lcmx_msgs/host_beacon_t.hpp"
#include "lcmx_msgs/records_t.hpp"
#include "lcmx_msgs/records_z_t.hpp"
#if __has_include("lcmx_msgs/marker_t.hpp")
#include "lcmx_msgs/marker_t.hpp"
#define LCMX_BENCH_HAVE_MARKER 1
#endif

namespace {
void item(const char* name, std::int64_t hash, bool last) {
  std::printf("\"%s\": \"%016" PRIx64 "\"%s", name, static_cast<std::uint64_t>(hash), last ? "" : ", ");
}
}  // namespace

int main() {
  std::printf("{");
  item("beacon_t", lcmx_msgs::beacon_t::getHash(), false);
  item("records_t", lcmx_msgs::records_t::getHash(), false);
  item("records_z_t", lcmx_msgs::records_z_t::getHash(), false);
  item("host_beacon_t", lcmx_msgs::host_beacon_t::getHash(), false);
#ifdef LCMX_BENCH_HAVE_MARKER
  item("marker_t", lcmx_msgs::marker_t::getHash(), true);
#else
  std::printf("\"marker_t\": null");
#endif
  std::printf("}\n");
  return 0;
}
