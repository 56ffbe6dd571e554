// lcmx: the command-line tool. Verbs: nodes, topics (more verbs come with later issues).
// It listens to discovery as an observer: it asks every participant to beacon at once and
// never appears as a participant itself.
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <iostream>
#include <thread>

#include "lcmx/core/options.hpp"
#include "lcmx/discovery/discovery.hpp"
#include "topology.hpp"

namespace {

std::vector<lcmx::discovery::Participant> observe(const std::string& url, int wait_ms) {
  lcmx::discovery::Options o;
  o.group = lcmx::udpm::parse_url(url);
  o.observer = true;
  lcmx::discovery::Discovery d(o, nullptr, nullptr);
  // Participants answer the query at once; a second query covers a lost datagram.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(wait_ms);
  std::this_thread::sleep_for(std::chrono::milliseconds(wait_ms / 2));
  d.query();
  std::this_thread::sleep_until(deadline);
  auto ps = d.participants();
  d.stop();
  return ps;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lcmx: inspect and operate an lcmx system (https://... see README.md)"};
  app.require_subcommand(1);
  std::string url = lcmx::RuntimeOptions::from_env().discovery_url;
  int wait_ms = 400;
  app.add_option("--url", url, "discovery group (default: LCMX_DISCOVERY_URL or LCM's default)")
      ->capture_default_str();
  app.add_option("--wait", wait_ms, "how long to listen for beacons, in milliseconds")
      ->check(CLI::Range(50, 60000))
      ->capture_default_str();

  auto* nodes = app.add_subcommand("nodes", "list participants (processes) and their nodes");
  auto* topics = app.add_subcommand(
      "topics", "list topics: type, publishers, subscribers, path per pair, rate, drops");

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e);
  }
  spdlog::set_level(spdlog::level::warn);
  try {
    const auto ps = observe(url, wait_ms);
    if (nodes->parsed()) lcmx::cli::print_nodes(std::cout, ps);
    if (topics->parsed()) lcmx::cli::print_topics(std::cout, ps);
  } catch (const std::exception& e) {
    std::cerr << "lcmx: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
