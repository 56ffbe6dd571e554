// Helpers of the DDS gateway's process tests: a DDS domain id and a Cyclone network config of
// the test's own (loopback only: unicast discovery to 127.0.0.1, no multicast, so nothing
// leaves the machine), a scratch folder, gateway config files, and the gateways' status.
#pragma once

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

namespace lcmx::ddstest {

// A domain id of its own for test `index` of this process (1..200: Cyclone's default port
// mapping has room up to 230), so tests run in parallel (ctest -j2) never meet.
inline int unique_domain(int index) { return 1 + static_cast<int>((::getpid() * 16u + index) % 200u); }

// Cyclone's config for a process on `iface` (address or name) that finds its peers by unicast.
inline std::string cyclone_uri(const std::string& iface, const std::vector<std::string>& peers) {
  const bool addr = iface.find('.') != std::string::npos;
  std::string x = "<General><Interfaces><NetworkInterface " + std::string(addr ? "address" : "name") + "=\"" + iface +
                  "\"/></Interfaces><AllowMulticast>false</AllowMulticast></General>"
                  "<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>60"
                  "</MaxAutoParticipantIndex><Peers>";
  for (const auto& p : peers) x += "<Peer address=\"" + p + "\"/>";
  return x + "</Peers></Discovery>";
}

// The environment of a plain DDS program (dds_peer) in domain `domain`.
inline std::vector<std::string> peer_env(int domain, const std::string& iface = "127.0.0.1",
                                         const std::vector<std::string>& peers = {"127.0.0.1"}) {
  return {"CYCLONEDDS_URI=" + cyclone_uri(iface, peers), "DDS_PEER_DOMAIN=" + std::to_string(domain)};
}

// The [gateway] part of a config on loopback: name, domain, network, types.
inline std::string gateway_head(const std::string& name, int domain, const std::string& iface = "127.0.0.1",
                                const std::string& peer = "127.0.0.1") {
  return "name = \"" + name + "\"\ndomain = " + std::to_string(domain) + "\ninterface = \"" + iface +
         "\"\nallow_multicast = false\npeers = [\"" + peer + "\"]\nstatus_period_ms = 200\ntypes = [\"" +
         LCMX_DDS_TEST_LCM + "\", \"" + LCMX_LCMTYPES_DIR + "\"]\n";
}

inline std::string mapping(const std::string& channel, const std::string& direction, const std::string& mode,
                           const std::string& type, const std::string& extra = "") {
  std::string m = "[[map]]\nchannel = \"" + channel + "\"\ndirection = \"" + direction + "\"\nmode = \"" + mode + "\"\n";
  if (!type.empty()) m += "type = \"" + type + "\"\n";
  return m + extra;
}

// A scratch folder, removed with everything in it.
class TempDir {
 public:
  explicit TempDir(const std::string& tag)
      : path_(std::filesystem::temp_directory_path() / ("lcmx_dds_" + tag + "_" + std::to_string(::getpid()))) {
    std::filesystem::create_directories(path_);
  }
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  std::string write(const std::string& name, const std::string& text) const {
    const auto p = path_ / name;
    std::ofstream(p) << text;
    return p.string();
  }
  const std::filesystem::path& path() const { return path_; }

 private:
  std::filesystem::path path_;
};

// The part of a `lcmx dds-gateway status --json` line about gateway `name` ("" if absent).
inline std::string gateway_json(const std::string& json, const std::string& name) {
  const auto b = json.find("{\"name\":\"" + name + "\"");
  if (b == std::string::npos) return {};
  const auto e = json.find("{\"name\":", b + 1);
  return json.substr(b, e == std::string::npos ? std::string::npos : e - b);
}

// The integer after "key": in `j` (first occurrence), or -1.
inline long long field(const std::string& j, const std::string& key) {
  const auto p = j.find("\"" + key + "\":");
  if (p == std::string::npos) return -1;
  return std::atoll(j.c_str() + p + key.size() + 3);
}

}  // namespace lcmx::ddstest
