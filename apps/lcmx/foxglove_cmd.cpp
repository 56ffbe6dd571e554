// `lcmx foxglove`: serves every lcmx channel to Foxglove and Lichtblick (lcmx::foxglove::Server)
// until SIGINT/SIGTERM. Prints one "ready" line on stdout once it listens (the URL to open),
// and a summary line at exit. Exit: 0 stopped by a signal, 1 cannot start (port in use, bad
// type path, bad TLS files), 2 bad arguments.
#include <malloc.h>
#include <spdlog/spdlog.h>

#include <cstdio>
#include <iostream>
#include <memory>

#include "foxglove_cmd.hpp"
#include "lcmx/foxglove/server.hpp"
#include "tap.hpp"

namespace lcmx::cli {
namespace {

struct FoxgloveArgs {
  std::string address = "127.0.0.1";
  int port = 8765;
  std::vector<std::string> types, channels, exclude, rates, publish_allow;
  std::string tls_cert, tls_key, name = "lcmx";
  bool client_publish = false, no_services = false, json = false;
  double queue_mb = 64;
  int queue_messages = 4096;
  double stats_s = 0;
};

// "[REGEX=]HZ" -> RateLimit; nullopt with *err set when it does not parse.
std::optional<foxglove::RateLimit> parse_rate(const std::string& s, std::string* err) {
  foxglove::RateLimit r;
  std::string hz = s;
  if (const auto eq = s.rfind('='); eq != std::string::npos) {
    r.pattern = s.substr(0, eq);
    hz = s.substr(eq + 1);
  }
  try {
    std::size_t used = 0;
    r.max_hz = std::stod(hz, &used);
    if (used != hz.size() || !(r.max_hz > 0)) throw std::invalid_argument("");
  } catch (const std::exception&) {
    *err = "--max-rate '" + s + "': expected [REGEX=]HZ with HZ > 0";
    return std::nullopt;
  }
  return r;
}

std::string stats_json(const foxglove::ServerStats& s) {
  auto n = [](auto v) { return std::to_string(v); };
  std::string j = "{\"clients\":" + n(s.clients) + ",\"channels\":" + n(s.channels) +
                  ",\"lcm_subscriptions\":" + n(s.lcm_subscriptions) + ",\"messages_in\":" + n(s.messages_in) +
                  ",\"messages_out\":" + n(s.messages_out) + ",\"dropped\":" + n(s.dropped) +
                  ",\"max_client_queue_bytes\":" + n(s.max_client_queue_bytes) +
                  ",\"rate_skipped\":" + n(s.rate_skipped) + ",\"decode_errors\":" + n(s.decode_errors) +
                  ",\"time\":" + (s.time ? "true" : "false") + ",\"per_client\":[";
  for (std::size_t i = 0; i < s.per_client.size(); ++i) {
    const auto& c = s.per_client[i];
    j += std::string(i ? "," : "") + "{\"remote\":\"" + c.remote + "\",\"queued_bytes\":" + n(c.queued_bytes) +
         ",\"queued_messages\":" + n(c.queued_messages) + ",\"dropped\":" + n(c.dropped) + "}";
  }
  return j + "]}";
}

int run(const FoxgloveArgs& a, const Globals& g) {
  foxglove::ServerOptions o;
  o.address = a.address;
  o.port = static_cast<std::uint16_t>(a.port);
  o.tls_cert = a.tls_cert;
  o.tls_key = a.tls_key;
  o.name = a.name;
  o.channels = a.channels;
  o.exclude = a.exclude;
  o.client_publish = a.client_publish;
  o.publish_allow = a.publish_allow;
  o.services = !a.no_services;
  o.client_queue_bytes = static_cast<std::size_t>(a.queue_mb * 1024 * 1024);
  o.client_queue_messages = static_cast<std::size_t>(a.queue_messages);
  for (const auto& r : a.rates) {
    std::string err;
    auto rl = parse_rate(r, &err);
    if (!rl) {
      std::cerr << "lcmx foxglove: " << err << "\n";
      return 2;
    }
    o.rate_limits.push_back(*rl);
  }
  if (a.tls_cert.empty() != a.tls_key.empty()) {
    std::cerr << "lcmx foxglove: --tls-cert and --tls-key go together\n";
    return 2;
  }
  try {
    auto reg = load_types(a.types);
    if (reg.size() == 0)
      std::cerr << "lcmx foxglove: warning: no type path (--types DIR|FILE or LCMX_TYPES_PATH): every channel "
                   "is shown as lcmx.unknown (raw bytes)\n";
    o.registry = std::make_shared<const types::TypeRegistry>(std::move(reg));
  } catch (const std::exception& e) {
    std::cerr << "lcmx foxglove: --types: " << e.what() << "\n";
    return 1;
  }
  // Images pass as multi-MB buffers (decoded, base64) many times a second: glibc keeps freed heap
  // memory for the next ones instead of giving it back and faulting it in again (page faults
  // were ~7 % of the server's CPU). Memory stays at its peak, which the client queues bound.
  ::mallopt(M_MMAP_THRESHOLD, 32 << 20);
  ::mallopt(M_TRIM_THRESHOLD, 512 << 20);
  try {
    StopSignals stop;  // before the runtime: lcmx's threads inherit the blocked mask
    o.runtime = runtime_options(g);
    foxglove::Server server(std::move(o));
    const std::string scheme = a.tls_cert.empty() ? "ws" : "wss";
    const std::string url = scheme + "://" + (a.address.find(':') != std::string::npos ? "[" + a.address + "]" : a.address) +
                            ":" + std::to_string(server.port());
    if (a.json)
      std::cout << "{\"ready\":true,\"url\":\"" << url << "\",\"port\":" << server.port() << "}" << std::endl;
    else
      std::cout << "lcmx foxglove: ready on " << url
                << " (open it in Foxglove or Lichtblick: \"Open connection\" > Foxglove WebSocket)" << std::endl;
    const auto period = std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::duration<double>(a.stats_s));
    while (!stop.wait(a.stats_s > 0 ? period : std::chrono::nanoseconds(-1))) {
      if (a.stats_s > 0) std::cout << stats_json(server.stats()) << std::endl;
    }
    const auto s = server.stats();
    if (a.json) std::cout << stats_json(s) << std::endl;
    else
      std::cout << "lcmx foxglove: stopped: " << s.messages_in << " messages received, " << s.messages_out
                << " queued to clients, " << s.dropped << " dropped for slow clients" << std::endl;
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "lcmx foxglove: " << e.what() << "\n";
    return 1;
  }
}

}  // namespace

Verb add_foxglove(CLI::App& app, const Globals& g) {
  auto a = std::make_shared<FoxgloveArgs>();
  auto* c = app.add_subcommand(
      "foxglove", "serve every channel live to Foxglove and Lichtblick (Foxglove WebSocket protocol)");
  c->add_option("--address", a->address,
                "address to listen on; the default keeps it on this machine, 0.0.0.0 opens it to every network")
      ->capture_default_str();
  c->add_option("--port", a->port, "TCP port (0: any free port, printed on the ready line)")
      ->check(CLI::Range(0, 65535))
      ->capture_default_str();
  c->add_option("-t,--types", a->types,
                ".lcm file or directory (searched recursively; repeatable, or a ':' list); default LCMX_TYPES_PATH")
      ->allow_extra_args(false);
  c->add_option("-c,--channel", a->channels,
                "advertise only channels matching this regex (whole name, ECMAScript; repeatable)")
      ->allow_extra_args(false);
  c->add_option("-x,--exclude", a->exclude, "never advertise channels matching this regex (repeatable)")
      ->allow_extra_args(false);
  c->add_option("--max-rate", a->rates,
                "[REGEX=]HZ: forward at most HZ messages a second of each channel (matching REGEX; "
                "repeatable, the first match applies)")
      ->allow_extra_args(false);
  c->add_flag("--client-publish", a->client_publish,
              "let clients publish typed LCM messages on any channel (Foxglove's Publish panel)");
  c->add_option("--publish-allow", a->publish_allow,
                "let clients publish on channels matching this regex only (repeatable; enables clientPublish)")
      ->allow_extra_args(false);
  c->add_flag("--no-services", a->no_services, "do not offer lcmx services to clients");
  c->add_option("--tls-cert", a->tls_cert, "PEM certificate (chain): serve wss:// (with --tls-key)")
      ->check(CLI::ExistingFile);
  c->add_option("--tls-key", a->tls_key, "PEM private key of --tls-cert")->check(CLI::ExistingFile);
  c->add_option("--queue-mb", a->queue_mb, "each client's queue bound in MiB (the oldest of its largest channels go first)")
      ->check(positive_number())
      ->capture_default_str();
  c->add_option("--queue-messages", a->queue_messages, "each client's queue bound in messages")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  c->add_option("--name", a->name, "server name shown by the clients")->capture_default_str();
  c->add_option("--stats", a->stats_s, "print counters as a JSON line every SECONDS")->check(positive_number());
  c->add_flag("--json", a->json, "ready line and summary as JSON");
  c->footer(
      "Channels are JSON with JSON Schemas from the .lcm files (docs/foxglove.md); image-shaped types also show "
      "as foxglove.RawImage / CompressedImage on CHANNEL/image, point clouds as foxglove.PointCloud on "
      "CHANNEL/points. Exit: 0 stopped by SIGINT/SIGTERM, 1 cannot start, 2 bad arguments.");
  return {c, [a, &g] { return run(*a, g); }};
}

}  // namespace lcmx::cli
