// lcmx_bench_udp: one-way latency and loss between two emulated hosts (bench/harness/hosts.hpp),
// lcmx's UDP path (Publisher<bench_t> -> Subscriber<bench_t> on another host over the vehicle
// group) side by side with raw liblcm udpm between the same namespaces, in one run (DESIGN.md
// "Benchmarks", experiment 1, UDP row).
//
//  - ping-pong per size (the harness's protocol, bench/harness/pingpong.hpp): acks go through a
//    pipe (pipes do not care about network namespaces), so the link only carries the measured
//    traffic. The methods run in --rounds rounds, in alternating order (liblcm, lcmx / lcmx,
//    liblcm, ...), and each method's rounds are pooled: slow drifts of a shared machine hit both
//    alike.
//  - stream, two scenarios per method: "idle" (--stream-messages messages of --stream-size at
//    --stream-rate Hz to an idle receiving host) and "busy" (the same messages in bursts of
//    --stream-burst back to back per tick, like a camera's frame set, while --stream-hogs CPU
//    hog processes run in the receiving host's namespace at the same nice level, started before
//    the subscriber for both methods alike). No acks; loss = sent - received.
//  - --keys: instead of liblcm, lcmx UDP three ways in one run: unkeyed, on a keyed vehicle
//    group authenticated, and encrypted (docs/keyed-groups.md), ping-pong rounds in rotating
//    order, then the idle stream for each with the CPU time of publisher + subscriber per MB.
//  - --seal-micro: what sealing one datagram costs per libsodium primitive (no network).
// Without --role this is the orchestrator: Markdown on stdout, progress on stderr. Root needed.
#include <sodium.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <span>
#include <sstream>

#include "harness/hosts.hpp"
#include "harness/options.hpp"
#include "harness/report.hpp"
#include "../../core/udpm/src/envelope.hpp"  // private: --seal-micro times the envelope's own tag
#include "lcmx/udpm/keys.hpp"
#include "udp/roles.hpp"

namespace lcmxbench::udp {
namespace {

const char* const kProgram = "lcmx_bench_udp";
void say(const std::string& s) { progress("bench-udp", s); }

constexpr const char* kDiscoveryUrl = "udpm://239.255.77.221:17721?ttl=0";  // each host's own lo
constexpr const char* kVehicleUrl = "udpm://239.255.77.222:17722?ttl=1&iface=eth";
constexpr const char* kLcmUrl = "udpm://239.255.77.223:17723?ttl=1";  // liblcm: the 224/4 route (eth)

struct Options {
  std::vector<std::string> sizes{"1K", "10K", "100K", "1M", "2M", "6M"};
  int messages = 0, warmup = -1, timeout_ms = 200;
  std::string stream_size = "100K";
  double stream_rate = 30;
  int stream_messages = 150;
  int stream_burst = 4, stream_hogs = 2;  // "busy" scenario
  int rounds = 3;
  bool no_stream = false;
  LinkOptions link;  // rate: tc tbf on the link ("" = none)
  std::string pin = "none";
  std::string markdown;
  bool keys = false;  // unkeyed / authenticated / encrypted lcmx instead of liblcm vs lcmx
};

struct Run {
  Options opt;
  std::vector<SizePlan> plan, stream_plan;
  lcmx::test::Emulation* emu = nullptr;
  std::string exe;
  Pinning cpus;
  int serial = 0;
  std::string key_file;  // --keys: the vehicle group key the keyed methods use
};

// Stream scenario: messages per tick and CPU hogs on the receiving host.
struct Scenario {
  std::string name = "idle";
  int burst = 1, hogs = 0;
};

// method: "liblcm" | "lcmx-udp" (ping-pong), "liblcm-stream" | "lcmx-udp-stream".
MethodResult run_method(Run& run, const std::string& method, const Scenario& sc = {}) {
  const bool stream = method.find("stream") != std::string::npos;
  const bool liblcm = method.rfind("liblcm", 0) == 0;
  // lcmx on a keyed vehicle group: "lcmx-udp-auth[-stream]", "lcmx-udp-crypt[-stream]".
  const bool auth = method.find("-auth") != std::string::npos, crypt = method.find("-crypt") != std::string::npos;
  const auto& plan = stream ? run.stream_plan : run.plan;
  say(method + ": starting");
  const std::int64_t t0 = now_ns();
  std::int64_t budget_ms = 40'000;
  for (const auto& p : plan)
    budget_ms += stream ? static_cast<std::int64_t>(p.messages * 1000 / run.opt.stream_rate) + 5000
                        : static_cast<std::int64_t>(p.warmup + p.messages) * (run.opt.timeout_ms + 50);
  const std::string name = "UDP_" + std::to_string(::getpid()) + "_" + std::to_string(++run.serial);
  auto args = [&](const std::string& role) {
    std::vector<std::string> a{
        run.exe, "--role", role, "--plan", plan_to_string(plan), "--name", name, "--url",
        liblcm ? kLcmUrl : kDiscoveryUrl, "--vehicle-url", kVehicleUrl, "--timeout-ms",
        std::to_string(run.opt.timeout_ms), "--stream-rate", std::to_string(run.opt.stream_rate),
        "--stream-burst", std::to_string(sc.burst)};
    if (auth || crypt) a.insert(a.end(), {"--key-file", run.key_file});
    if (crypt) a.push_back("--crypt");
    return a;
  };
  const std::string base = liblcm ? "liblcm" : "lcmx-udp";
  Pair pair;
  pair.method = method;
  pair.sub_argv = args(base + (stream ? "-stream-sub" : "-sub"));
  pair.pub_argv = args(base + (stream ? "-stream-pub" : "-pub"));
  pair.sub_netns = run.emu->ns_fd(1);
  pair.pub_netns = run.emu->ns_fd(0);
  pair.sub_cpu = run.cpus.sub;
  pair.pub_cpu = run.cpus.pub;
  pair.deadline_ms = static_cast<int>(budget_ms);
  // Hogs first, unpinned, so the subscriber starts on an already busy host.
  std::vector<pid_t> hogs;
  for (int i = 0; i < sc.hogs; ++i) hogs.push_back(spawn_child({run.exe, "--role", "hog"}, {}, -1, run.emu->ns_fd(1)));
  MethodResult res = run_pair(pair).result;
  for (auto p : hogs) reap_child(p, 0);  // SIGKILLed and reaped
  progress_of("bench-udp", res, plan);
  char t[64];
  std::snprintf(t, sizeof t, "%.1f s", static_cast<double>(now_ns() - t0) / 1e9);
  say(method + ": finished in " + t);
  return res;
}

struct StreamResult {
  Scenario sc;
  MethodResult lcm, lx;
};

// Reads a one-number /proc/sys file ("?" if unreadable).
std::string sysctl(const char* path) {
  std::ifstream in(path);
  std::string v;
  return in >> v ? v : "?";
}

std::string report(const Run& run, const MethodResult& lcm, const MethodResult& lx,
                   const std::vector<StreamResult>& streams) {
  std::ostringstream md;
  md << "## lcmx UDP vs raw liblcm udpm between two emulated hosts\n\n";
  md << "- " << machine_line() << "; pinning `--pin " << run.opt.pin << "`\n";
  md << "- 2 network namespaces joined by a veth/bridge link"
     << (run.opt.link.rate.empty() ? " (no rate limit)" : " shaped to " + run.opt.link.rate + " (tbf)")
     << "; publisher on host 0, subscriber on host 1\n";
  md << "- lcmx: Publisher<bench_t> -> Subscriber<bench_t>, vehicle group `" << kVehicleUrl
     << "` (path udp; messages > udp_limit make the topic large and go as LC03 fragments), receive "
        "buffer 4 MiB (GroupConfig default, SO_RCVBUFFORCE), subscriber node `block`; liblcm: "
        "lcm_publish -> lcm_handle on `" << kLcmUrl << "`, kernel default receive buffer "
        "(net.core.rmem_default " << sysctl("/proc/sys/net/core/rmem_default") << ", rmem_max "
     << sysctl("/proc/sys/net/core/rmem_max") << ")\n";
  md << "- ping-pong rounds: " << run.opt.rounds
     << " per method, alternating order (liblcm first in odd rounds, lcmx first in even ones), "
        "pooled\n";
  md << "- ping-pong: next message after the ack (pipe side channel, not on the link) or after "
     << run.opt.timeout_ms << " ms = lost; messages per size (warmup + measured): " << plan_text(run.plan);
  md << "\n- cells: p50 / p99 one-way µs (send_ns before encode -> after decode, shared "
        "CLOCK_MONOTONIC), lost/sent; ratio = lcmx p50 / liblcm p50\n\n";
  Table table({"size", "liblcm udpm", "lcmx UDP", "lcmx/liblcm"});
  double worst = 0;
  std::size_t worst_size = 0;
  bool compared = false, missing = false;
  for (const auto& p : run.plan) {
    const Cell a = cell_of(lcm, p.size), b = cell_of(lx, p.size);
    std::string ratio = "—";
    if (a.ok && b.ok && a.st.n && b.st.n) {
      ratio = fmt_ratio(b.st.p50 / a.st.p50);
      if (a.lost == 0) {
        compared = true;
        if (b.st.p50 / a.st.p50 > worst) worst = b.st.p50 / a.st.p50, worst_size = p.size;
      }
    } else if (a.ok && a.lost == 0) {
      missing = true;
    }
    table.row({size_label(p.size), cell_text(lcm, p.size, true), cell_text(lx, p.size, true), ratio});
  }
  md << table.markdown();
  md << "\n**Targets**\n";
  md << "- lcmx UDP within 1.1x of raw liblcm at every size where liblcm loses nothing: ";
  if (!compared) md << "not measured (no size where both delivered and liblcm lost nothing)";
  else md << verdict(worst <= 1.1 && !missing) << " (worst " << fmt_ratio(worst) << " at " << size_label(worst_size)
          << (missing ? "; lcmx has no result at a size where liblcm lost nothing" : "") << ")";
  md << "\n";
  if (!streams.empty()) {
    const auto& sp = run.stream_plan.front();
    Table table({"scenario", "liblcm udpm", "lcmx UDP"});
    for (const auto& r : streams) {
      table.row({r.sc.name + ": " + std::to_string(r.sc.burst) + " message" + (r.sc.burst > 1 ? "s" : "") +
                     " per tick, " + std::to_string(r.sc.hogs) + " CPU hog" + (r.sc.hogs == 1 ? "" : "s") +
                     " on the receiving host",
                 cell_text(r.lcm, sp.size, true), cell_text(r.lx, sp.size, true)});
      const Cell a = cell_of(r.lcm, sp.size), b = cell_of(r.lx, sp.size);
      md << "- no loss at " << size_label(sp.size) << " and " << run.opt.stream_rate << " Hz where liblcm "
         << "with default buffers loses some (" << r.sc.name << "): ";
      if (!a.ok || !b.ok) md << "not measured (a stream run failed)";
      else if (b.lost > 0) md << "**FAILS** (lcmx lost " << b.lost << "/" << b.sent << ", liblcm " << a.lost << "/" << a.sent << ")";
      else if (a.lost == 0) md << "lcmx lost nothing; liblcm lost nothing either in this run (no contrast)";
      else md << "**holds** (lcmx lost 0/" << b.sent << ", liblcm lost " << a.lost << "/" << a.sent << ")";
      md << "\n";
    }
    md << "\nStream: " << sp.messages << " messages of " << size_label(sp.size) << ", " << run.opt.stream_rate
       << " ticks/s, no acks; cells: p50 / p99 one-way µs (lost/sent)\n\n"
       << table.markdown() << "\n";
  } else {
    md << "- stream target: not measured (--no-stream)\n";
  }
  md << "- (differences under 1.3x are noise on this 2-vCPU machine, DESIGN.md \"Measuring\")\n";
  std::vector<const MethodResult*> all = {&lcm, &lx};
  for (const auto& r : streams) all.push_back(&r.lcm), all.push_back(&r.lx);
  std::vector<std::pair<std::string, std::string>> failures, notes;
  for (const MethodResult* m : all) {
    for (const auto& e : m->errors) failures.emplace_back(m->method, e);
    for (const auto& n : m->notes) notes.emplace_back(m->method, n);
  }
  md << list_section("Failures", failures) << list_section("Notes", notes);
  return md.str();
}

// The CPU time (µs) of the children's "note cpu <who> <µs>" lines of `m`.
long long cpu_us(const MethodResult& m) {
  long long sum = 0;
  for (const auto& n : m.notes) {
    std::istringstream in(n);
    std::string cpu, who;
    long long us = 0;
    if (in >> cpu >> who >> us && cpu == "cpu") sum += us;
  }
  return sum;
}

// --keys: the three lcmx modes side by side.
std::string report_keys(const Run& run, const std::vector<MethodResult>& pp, const std::vector<MethodResult>& st) {
  std::ostringstream md;
  md << "## lcmx UDP unkeyed, authenticated and encrypted (keyed groups) between two emulated hosts\n\n";
  md << "- " << machine_line() << "; pinning `--pin " << run.opt.pin << "`\n";
  md << "- Publisher<bench_t> on host 0 -> Subscriber<bench_t> on host 1 over the vehicle group `" << kVehicleUrl
     << "`; keyed: XChaCha20-Poly1305 (libsodium) per datagram, authenticated (tag over header and datagram) or "
        "encrypted (datagram encrypted, header authenticated)\n";
  md << "- ping-pong rounds: " << run.opt.rounds << " per mode, rotating order, pooled; messages per size (warmup + "
        "measured): " << plan_text(run.plan) << "\n";
  md << "- cells: p50 / p99 one-way µs (lost/sent); ratios: keyed p50 / unkeyed p50\n\n";
  auto ratio = [&](const MethodResult& a, const MethodResult& b, std::size_t size) -> std::pair<std::string, double> {
    const Cell x = cell_of(a, size), y = cell_of(b, size);
    if (!x.ok || !y.ok || !x.st.n || !y.st.n) return {"—", 0};
    return {fmt_ratio(y.st.p50 / x.st.p50, 3), y.st.p50 / x.st.p50};
  };
  Table table({"size", "unkeyed", "authenticated", "encrypted", "auth/unkeyed", "crypt/unkeyed"});
  for (const auto& p : run.plan)
    table.row({size_label(p.size), cell_text(pp[0], p.size, true), cell_text(pp[1], p.size, true),
               cell_text(pp[2], p.size, true), ratio(pp[0], pp[1], p.size).first, ratio(pp[0], pp[2], p.size).first});
  md << table.markdown();
  md << "\n**Targets**\n";
  const std::size_t k1 = 1024;
  if (std::any_of(run.plan.begin(), run.plan.end(), [&](const SizePlan& p) { return p.size == k1; })) {
    const auto a = ratio(pp[0], pp[1], k1), c = ratio(pp[0], pp[2], k1);
    md << "- 1 KB p50 authenticated within 3 % of unkeyed: "
       << (a.second == 0 ? std::string("not measured") : verdict(a.second <= 1.03)) << " (" << a.first << ")\n";
    md << "- 1 KB p50 encrypted within 10 % of unkeyed: "
       << (c.second == 0 ? std::string("not measured") : verdict(c.second <= 1.10)) << " (" << c.first << ")\n";
  }
  if (!st.empty()) {
    const auto& sp = run.stream_plan.front();
    const double mb = static_cast<double>(sp.size) * sp.messages / 1e6;
    bool all = true, measured = true;
    for (const auto& m : st) {
      const Cell c = cell_of(m, sp.size);
      measured = measured && c.ok;
      all = all && c.ok && c.lost == 0;
    }
    md << "- " << size_label(sp.size) << " at " << run.opt.stream_rate << " Hz with 0 lost in all three: "
       << (!measured ? std::string("not measured") : verdict(all)) << "\n";
    md << "\nStream: " << sp.messages << " messages of " << size_label(sp.size) << " at " << run.opt.stream_rate
       << " Hz, no acks; CPU: user + system time of the publisher and subscriber processes (the whole run, start-up "
          "and discovery included) per MB of payload\n\n";
    Table s({"mode", "p50 / p99 one-way µs (lost/sent)", "CPU ms (pub + sub)", "CPU ms per MB"});
    const char* names[3] = {"unkeyed", "authenticated", "encrypted"};
    for (std::size_t i = 0; i < st.size(); ++i) {
      char cpu[64], per[64];
      std::snprintf(cpu, sizeof cpu, "%.0f", static_cast<double>(cpu_us(st[i])) / 1000.0);
      std::snprintf(per, sizeof per, "%.2f", static_cast<double>(cpu_us(st[i])) / 1000.0 / mb);
      s.row({names[i], cell_text(st[i], sp.size, true), cpu, per});
    }
    md << s.markdown() << "\n";
  }
  md << "- (differences of a few per cent are within the noise of this 2-vCPU machine, DESIGN.md \"Measuring\"; "
        "more --rounds narrow them)\n";
  std::vector<std::pair<std::string, std::string>> failures;
  for (const auto* v : {&pp, &st})
    for (const auto& m : *v)
      for (const auto& e : m.errors) failures.emplace_back(m.method, e);
  md << list_section("Failures", failures);
  return md.str();
}

// --seal-micro: what each candidate primitive costs per datagram, in this process (no network):
// the choice of docs/keyed-groups.md "Wire form". Median of 7 runs of N calls each, after one
// untimed run; then the chosen two and version 1's authentication with cold caches.
int seal_micro() {
  if (::sodium_init() < 0) return 1;
  unsigned char key[32], nonce[24] = {}, tag[64], out[64], none = 0;
  ::randombytes_buf(key, sizeof key);
  using Fn = std::function<void(std::span<unsigned char>, std::span<unsigned char>, std::size_t)>;
  unsigned char otk[32];
  ::crypto_stream_chacha20_ietf(otk, sizeof otk, nonce, key);
  // The envelope's tag with the one-time key made ahead (core/udpm/src/envelope.cpp).
  const auto tag_ahead = [&](const unsigned char* ad, std::size_t ad_size, const unsigned char* c, std::size_t c_size) {
    unsigned char t[lcmx::udpm::kEnvelopeTagSize];
    lcmx::udpm::detail::tag_of(t, otk, ad, ad_size, c, c_size);
    std::memcpy(tag, t, sizeof t);
  };
  const std::vector<std::pair<std::string, Fn>> rows = {
      {"ChaCha20-Poly1305-IETF's tag (subkey kept) with the one-time key made ahead, datagram as AD "
       "(authenticated, chosen)",
       [&](auto m, auto, std::size_t n) { tag_ahead(m.data(), n + 32, nullptr, 0); }},
      {"the same in one AEAD call, one-time key made in it (crypto_aead_chacha20poly1305_ietf, envelope "
       "version 2 before 9dee8e6), authenticated",
       [&](auto m, auto, std::size_t n) {
         ::crypto_aead_chacha20poly1305_ietf_encrypt_detached(&none, tag, nullptr, &none, 0, m.data(), n + 32, nullptr,
                                                              nonce, key);
       }},
      {"ChaCha20 from block 1 over the datagram, then the tag with the one-time key made ahead, 32-byte header "
       "as AD (encrypted, chosen)",
       [&](auto m, auto c, std::size_t n) {
         ::crypto_stream_chacha20_ietf_xor_ic(c.data(), m.data() + 32, n, nonce, 1, key);
         tag_ahead(m.data(), 32, c.data(), n);
       }},
      {"the same in one AEAD call (before 9dee8e6), encrypted",
       [&](auto m, auto c, std::size_t n) {
         ::crypto_aead_chacha20poly1305_ietf_encrypt_detached(c.data(), tag, nullptr, m.data() + 32, n, m.data(), 32,
                                                              nullptr, nonce, key);
       }},
      {"XChaCha20-Poly1305, HChaCha20 each call (envelope version 1), authenticated",
       [&](auto m, auto, std::size_t n) {
         ::crypto_aead_xchacha20poly1305_ietf_encrypt_detached(&none, tag, nullptr, &none, 0, m.data(), n + 32, nullptr,
                                                               nonce, key);
       }},
      {"XChaCha20-Poly1305, HChaCha20 each call (envelope version 1), encrypted",
       [&](auto m, auto c, std::size_t n) {
         ::crypto_aead_xchacha20poly1305_ietf_encrypt_detached(c.data(), tag, nullptr, m.data() + 32, n, m.data(), 32,
                                                               nullptr, nonce, key);
       }},
      {"HChaCha20 alone (XChaCha20's per-nonce subkey)",
       [&](auto, auto, std::size_t) { ::crypto_core_hchacha20(out, nonce, key, nullptr); }},
      {"ChaCha20 block alone (crypto_stream_chacha20_ietf, 32 bytes: Poly1305's one-time key)",
       [&](auto, auto, std::size_t) { ::crypto_stream_chacha20_ietf(out, 32, nonce, key); }},
      {"Poly1305 alone (crypto_onetimeauth), datagram",
       [&](auto m, auto, std::size_t n) { ::crypto_onetimeauth(tag, m.data(), n + 32, key); }},
      {"memcpy of the datagram (the envelope's copy into the sealing buffer)",
       [&](auto m, auto c, std::size_t n) {
         std::memcpy(c.data(), m.data(), n);
         asm volatile("" : : "r"(c.data()) : "memory");
       }},
      {"crypto_auth (HMAC-SHA-512-256)", [&](auto m, auto, std::size_t n) { ::crypto_auth(out, m.data(), n + 32, key); }},
      {"crypto_generichash keyed (BLAKE2b-128)",
       [&](auto m, auto, std::size_t n) { ::crypto_generichash(out, 16, m.data(), n + 32, key, sizeof key); }},
      {"AES-256-GCM, empty message, datagram as AD (x86-64 AES-NI only)",
       [&](auto m, auto, std::size_t n) {
         if (::crypto_aead_aes256gcm_is_available())
           ::crypto_aead_aes256gcm_encrypt_detached(&none, tag, nullptr, &none, 0, m.data(), n + 32, nullptr, nonce, key);
       }},
  };
  std::cout << "| per datagram | 1 KB (ns) | 64 KB (ns) |\n|---|---|---|\n";
  // One datagram and one output buffer, 64-byte aligned, for every row: Poly1305's speed moves
  // by ~100 ns at 1 KB with where a fresh allocation lands.
  struct Buffers {
    std::vector<unsigned char> m_raw, c_raw;
    std::span<unsigned char> m, c;
    explicit Buffers(std::size_t size) : m_raw(size + 32 + 64), c_raw(size + 64 + 64) {
      const auto aligned = [](std::vector<unsigned char>& v, std::size_t n) {
        const auto skip = (64 - reinterpret_cast<std::uintptr_t>(v.data()) % 64) % 64;
        return std::span<unsigned char>(v.data() + skip, n);
      };
      m = aligned(m_raw, size + 32);
      c = aligned(c_raw, size + 64);
      ::randombytes_buf(m.data(), m.size());
    }
  };
  std::map<std::size_t, Buffers> buffers;
  for (const std::size_t size : {std::size_t{64}, std::size_t{1024}, std::size_t{65000}}) buffers.try_emplace(size, size);
  for (const auto& [name, f] : rows) {
    std::cout << "| " << name;
    for (const std::size_t size : {std::size_t{1024}, std::size_t{65000}}) {
      auto& [m_raw, c_raw, m, c] = buffers.at(size);
      const int n = size == 1024 ? 20000 : 400;
      std::vector<double> runs;
      for (int i = 0; i < n; ++i) f(m, c, size);  // warm-up, untimed (the first row ran cold)
      for (int r = 0; r < 7; ++r) {
        const auto t0 = std::chrono::steady_clock::now();
        for (int i = 0; i < n; ++i) {
          nonce[0] = static_cast<unsigned char>(i);
          f(m, c, size);
        }
        runs.push_back(std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now() - t0).count() / n);
      }
      std::sort(runs.begin(), runs.end());
      if (name.rfind("AES", 0) == 0 && !::crypto_aead_aes256gcm_is_available()) std::cout << " | not available";
      else std::cout << " | " << static_cast<long long>(runs[3]);
    }
    std::cout << " |\n";
  }
  // The same calls with cold caches, as on a pipeline that sleeps between messages (a ping-pong,
  // a 30 Hz sensor): before each call a 64 MiB sweep evicts the code and data the call uses.
  // Median of 201 calls (1 KB) and 41 (64 KB).
  std::vector<unsigned char> sweep(64u << 20);
  std::cout << "\n| per datagram, caches swept before each call | 64 B (ns) | 1 KB (ns) | 64 KB (ns) |\n|---|---|---|---|\n";
  for (std::size_t row : {std::size_t{0}, std::size_t{1}, std::size_t{2}, std::size_t{3}, std::size_t{7},
                          std::size_t{8}, rows.size() - 1}) {
    const auto& [name, f] = rows[row];
    std::cout << "| " << name;
    for (const std::size_t size : {std::size_t{64}, std::size_t{1024}, std::size_t{65000}}) {
      auto& [m_raw, c_raw, m, c] = buffers.at(size);
      const int n = size == 65000 ? 41 : 201;
      std::vector<double> calls;
      for (int i = 0; i < n; ++i) {
        for (std::size_t j = 0; j < sweep.size(); j += 64) sweep[j] = static_cast<unsigned char>(sweep[j] + 1);
        nonce[0] = static_cast<unsigned char>(i);
        const auto t0 = std::chrono::steady_clock::now();
        f(m, c, size);
        calls.push_back(std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now() - t0).count());
      }
      std::sort(calls.begin(), calls.end());
      std::cout << " | " << static_cast<long long>(calls[calls.size() / 2]);
    }
    std::cout << " |\n";
  }
  return 0;
}

int orchestrate(const Options& opt) {
  Run run;
  run.opt = opt;
  try {
    run.plan = make_plan(opt.sizes, {{10, 5, 3}, {100, 50, 30}}, opt.messages, opt.warmup);
    run.stream_plan.push_back({parse_size(opt.stream_size, 16), 0, opt.stream_messages});
  } catch (const std::exception& e) {
    return bad_options(kProgram, e.what());
  }
  if (const auto why = bad_link_options(opt.link)) return bad_options(kProgram, *why);
  if (opt.pin == "split")
    if (const auto why = split_unavailable()) return bad_options(kProgram, *why);
  run.cpus = pinning(opt.pin);
  if (const auto why = hosts_unavailable()) {
    std::cerr << kProgram << ": " << *why << "\n";
    return 1;
  }
  on_stop_signals(OnStop::flag);
  run.exe = self_exe();
  LinkOptions link = opt.link;
  link.tcp_congestion = "cubic";
  auto emu = emulate_hosts(link);
  run.emu = &emu;
  say("hosts: " + hosts_line(emu));
  if (opt.keys) {
    // A key file for the keyed modes, in a directory of our own (removed at the end).
    std::string dir = "/tmp/lcmx_bench_keys_XXXXXX";
    if (::mkdtemp(dir.data()) == nullptr) {
      std::cerr << kProgram << ": mkdtemp: " << std::strerror(errno) << "\n";
      return 1;
    }
    run.key_file = dir + "/vehicle.key";
    lcmx::udpm::GroupKeys k;
    k.keys.push_back(lcmx::udpm::generate_key());
    lcmx::udpm::write_key_file(run.key_file, k, false);
    const std::vector<std::string> modes = {"lcmx-udp", "lcmx-udp-auth", "lcmx-udp-crypt"};
    std::vector<MethodResult> pp;
    for (const auto& m : modes) pp.push_back(MethodResult{m, {}, {}, {}});
    for (int r = 0; r < opt.rounds && !stopped(); ++r) {
      say("round " + std::to_string(r + 1) + " of " + std::to_string(opt.rounds));
      for (std::size_t i = 0; i < modes.size(); ++i) {
        const std::size_t m = (i + static_cast<std::size_t>(r)) % modes.size();  // rotating order
        merge(pp[m], run_method(run, modes[m]));
      }
    }
    std::vector<MethodResult> st;
    if (!opt.no_stream)
      for (const auto& m : modes) {
        if (stopped()) break;
        st.push_back(run_method(run, m + "-stream", Scenario{"idle", 1, 0}));
      }
    ::unlink(run.key_file.c_str());
    ::rmdir(dir.c_str());
    if (stopped()) {
      std::cerr << kProgram << ": interrupted\n";
      return 128 + stop_flag().load();
    }
    bool ok = print_report(kProgram, report_keys(run, pp, st), opt.markdown);
    for (const auto* v : {&pp, &st})
      for (const auto& m : *v) ok = ok && m.errors.empty();
    return ok ? 0 : 1;
  }
  MethodResult lcm{"liblcm", {}, {}, {}}, lx{"lcmx-udp", {}, {}, {}};
  for (int r = 0; r < opt.rounds && !stopped(); ++r) {
    say("round " + std::to_string(r + 1) + " of " + std::to_string(opt.rounds));
    if (r % 2 == 0) {
      merge(lcm, run_method(run, "liblcm"));
      merge(lx, run_method(run, "lcmx-udp"));
    } else {
      merge(lx, run_method(run, "lcmx-udp"));
      merge(lcm, run_method(run, "liblcm"));
    }
  }
  std::vector<StreamResult> streams;
  if (!opt.no_stream && !stopped()) {
    for (const Scenario& sc : {Scenario{"idle", 1, 0}, Scenario{"busy", opt.stream_burst, opt.stream_hogs}}) {
      say("stream scenario " + sc.name);
      StreamResult r{sc, run_method(run, "liblcm-stream", sc), run_method(run, "lcmx-udp-stream", sc)};
      streams.push_back(std::move(r));
    }
  }
  if (stopped()) {
    std::cerr << kProgram << ": interrupted\n";
    return 128 + stop_flag().load();
  }
  bool ok = print_report(kProgram, report(run, lcm, lx, streams), opt.markdown);
  ok = ok && lx.errors.empty() && lcm.errors.empty();
  for (const auto& r : streams) ok = ok && r.lcm.errors.empty() && r.lx.errors.empty();
  return ok ? 0 : 1;
}

}  // namespace
}  // namespace lcmxbench::udp

int main(int argc, char** argv) {
  using namespace lcmxbench;
  using namespace lcmxbench::udp;
  CLI::App app{
      "lcmx_bench_udp: one-way latency p50/p99 and loss between two emulated hosts (network\n"
      "namespaces), lcmx's UDP path vs raw liblcm udpm, ping-pong by size plus a fixed-rate\n"
      "stream, in one run. Markdown on stdout, progress on stderr. Needs root."};
  Options opt;
  app.add_option("--sizes", opt.sizes, "ping-pong sizes (K = 1024, M = 1024*1024)")->delimiter(',')->capture_default_str();
  app.add_option("--messages", opt.messages, "measured messages per size (default 100 up to 100 KB, 50 up to 2 MB, 30 above)")
      ->check(CLI::PositiveNumber);
  app.add_option("--warmup", opt.warmup, "unmeasured messages per size first (default 10 / 5 / 3)")->check(CLI::NonNegativeNumber);
  app.add_option("--timeout-ms", opt.timeout_ms, "ack timeout per message; then it counts as lost")
      ->check(CLI::Range(10, 10000))->capture_default_str();
  app.add_option("--stream-size", opt.stream_size, "stream message size")->capture_default_str();
  app.add_option("--stream-rate", opt.stream_rate, "stream rate in Hz")->check(CLI::Range(1.0, 100000.0))->capture_default_str();
  app.add_option("--stream-messages", opt.stream_messages, "stream messages")->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--stream-burst", opt.stream_burst, "busy stream scenario: messages sent back to back per tick")
      ->check(CLI::Range(1, 1000))->capture_default_str();
  app.add_option("--stream-hogs", opt.stream_hogs, "busy stream scenario: CPU hog processes on the receiving host")
      ->check(CLI::Range(0, 64))->capture_default_str();
  app.add_option("--rounds", opt.rounds, "ping-pong rounds per method, alternating order, pooled")
      ->check(CLI::Range(1, 100))->capture_default_str();
  app.add_flag("--no-stream", opt.no_stream, "skip the stream runs");
  add_link_options(app, opt.link, "shape the link with tc tbf (e.g. 10gbit, 1gbit); default: none", false);
  add_pin_option(app, opt.pin, {"none", "same", "split"}, "CPU pinning: none, same (both on CPU 0), split (pub 0, sub 1)");
  app.add_option("--markdown", opt.markdown, "also write the Markdown report to this file");
  app.add_flag("--keys", opt.keys,
               "keyed groups: lcmx UDP unkeyed, authenticated and encrypted side by side (no liblcm), then the "
               "idle stream of each with CPU per MB (docs/keyed-groups.md)");
  bool micro = false;
  app.add_flag("--seal-micro", micro, "print what sealing one datagram costs per primitive (keyed groups), then exit");
  // The children.
  UdpConfig u;
  std::string plan;
  add_hidden(app, "--role", u.base.role);
  add_hidden(app, "--plan", plan);
  add_hidden(app, "--name", u.base.name);
  add_hidden(app, "--url", u.base.url);
  add_hidden(app, "--vehicle-url", u.vehicle_url);
  add_hidden(app, "--key-file", u.key_file);
  app.add_flag("--crypt", u.crypt)->group("");
  CLI11_PARSE(app, argc, argv);
  if (micro) return seal_micro();
  if (u.base.role.empty()) return orchestrate(opt);
  if (u.base.role == "hog") return run_hog();
  try {
    u.base.plan = plan_from_string(plan);
  } catch (const std::exception& e) {
    report_error(e.what());
    return 2;
  }
  u.base.timeout_ms = opt.timeout_ms;
  u.rate_hz = opt.stream_rate;
  u.burst = opt.stream_burst;
  const auto& r = u.base.role;
  if (r == "liblcm-sub") return run_liblcm_sub(u.base);
  if (r == "liblcm-pub") return run_liblcm_pub(u.base);
  if (r == "lcmx-udp-sub") return run_lcmx_udp_sub(u, false);
  if (r == "lcmx-udp-pub") return run_lcmx_udp_pub(u, false);
  if (r == "lcmx-udp-stream-sub") return run_lcmx_udp_sub(u, true);
  if (r == "lcmx-udp-stream-pub") return run_lcmx_udp_pub(u, true);
  if (r == "liblcm-stream-sub") return run_liblcm_stream_sub(u);
  if (r == "liblcm-stream-pub") return run_liblcm_stream_pub(u);
  report_error("unknown role " + r);
  return 2;
}
