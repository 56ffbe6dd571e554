#include "hosts.hpp"

#include <fstream>

namespace lcmxbench {

void add_link_options(CLI::App& app, LinkOptions& link, const std::string& rate_help, bool tcp) {
  app.add_option("--link-rate", link.rate, rate_help)->capture_default_str();
  if (tcp)
    app.add_option("--tcp-congestion", link.tcp_congestion,
                   "the hosts' TCP congestion control (Linux's default cubic; \"\" = this machine's, e.g. bbr, whose "
                   "pacing slows 1 MB bursts; bench/README.md \"TCP congestion control\")")
        ->capture_default_str();
}

std::optional<std::string> bad_link_options(const LinkOptions& link) {
  if (link.rate.empty()) return std::nullopt;
  try {
    if (lcmx::test::rate_bytes_per_second(link.rate) > 0) return std::nullopt;
  } catch (const std::exception&) {
  }
  return "--link-rate '" + link.rate + "': use a tc rate, e.g. 400mbit, 2gbit, 10gbit (\"\" = not shaped)";
}

double link_bits_per_second(const LinkOptions& link) {
  if (link.rate.empty()) return 0;
  try {
    return 8 * lcmx::test::rate_bytes_per_second(link.rate);
  } catch (const std::exception&) {
    return 0;
  }
}

std::optional<std::string> hosts_unavailable() {
  std::string why;
  if (lcmx::test::netns_available(&why)) return std::nullopt;
  return "cannot emulate hosts: " + why;
}

lcmx::test::Emulation emulate_hosts(const LinkOptions& link, int hosts) {
  lcmx::test::LinkSpec eth;
  eth.name = "eth";
  if (!link.rate.empty()) eth.rate = link.rate;
  return lcmx::test::Emulation::create({.hosts = hosts, .links = {eth}, .tcp_congestion = link.tcp_congestion});
}

std::string hosts_line(const lcmx::test::Emulation& emu) {
  return "A " + emu.ns(0) + " (" + emu.address(0, "eth") + ") -> B " + emu.ns(1) + " (" + emu.address(1, "eth") + ")";
}

std::string write_bridge_config(const lcmx::test::Emulation& emu, int host, const std::string& dir,
                                const std::string& prefix, const std::string& body) {
  const char* const side[] = {"A", "B"};
  const std::string path = dir + "/" + prefix + side[host] + ".toml";
  std::ofstream f(path);
  f << "# written by " << prefix << " (bench/harness)\n"
    << "name = \"" << prefix << side[host] << "\"\n"
    << "listen = [\"" << emu.address(host, "eth") << "\"]\n"
    << "control_port = 7700\n"
    << body << "\n"
    << "[[peer]]\nname = \"" << prefix << side[1 - host] << "\"\n"
    << "endpoints = [ { link = \"eth\", address = \"" << emu.address(1 - host, "eth") << "\" } ]\n";
  f.close();
  if (!f) throw std::runtime_error("cannot write " + path);
  return path;
}

std::string tcp_congestion_of(lcmx::test::Emulation& emu, int host) {
  std::string cc;
  emu.run_in(host, [&] { std::ifstream("/proc/sys/net/ipv4/tcp_congestion_control") >> cc; });
  return cc;
}

}  // namespace lcmxbench
