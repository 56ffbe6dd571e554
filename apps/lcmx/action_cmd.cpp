// `lcmx actions`: the actions discovery sees (servers announce "<name>/status" publishers of
// lcmx_msgs.action_status_t in their beacons, clients subscribe to it), each with its types,
// servers, clients and goals, from one status message of each (servers publish it at once to a
// new subscriber, and every status_period).
// `lcmx action send NAME [JSON]`: one goal, written as JSON and encoded with the `.lcm` files
// of the type path (the server's status names its types by fingerprint); feedback printed as
// it comes, then the outcome. SIGINT/SIGTERM cancels the goal and waits for its end.
// Threads: the main thread does everything; feedback arrives on the client's own thread
// (it prints under a mutex).
#include <spdlog/spdlog.h>

#include <condition_variable>
#include <cstdio>
#include <cstring>
#include <iostream>
#include <map>
#include <mutex>

#include "lcmx/core.hpp"
#include "lcmx/types/value.hpp"
#include "lcmx_msgs/action_status_t.hpp"
#include "log_common.hpp"
#include "service_cmds.hpp"
#include "tap.hpp"
#include "topology.hpp"

namespace lcmx::cli {
namespace {

using Clock = std::chrono::steady_clock;
using ms = std::chrono::milliseconds;
const std::string kStatusSuffix = "/status";

std::string state_name(std::int8_t s) {
  return s >= 0 && s <= 7 ? to_string(static_cast<GoalState>(s)) : "?";
}

// Waits up to `timeout` (or a stop, if `stop`) for one status message on each of `names`'
// status channels.
std::map<std::string, lcmx_msgs::action_status_t> read_statuses(Node& node, const std::vector<std::string>& names,
                                                                ms timeout, StopSignals* stop) {
  std::mutex mu;
  std::condition_variable cv;
  std::map<std::string, lcmx_msgs::action_status_t> got;
  std::vector<RawSubscriber> subs;
  for (const auto& n : names)
    subs.push_back(node.subscribe_raw(n + kStatusSuffix, [&, n](const RawMessage& m) {
      lcmx_msgs::action_status_t s;
      if (m.data.size() > static_cast<std::size_t>(INT32_MAX) ||
          s.decode(m.data.data(), 0, static_cast<int>(m.data.size())) < 0)
        return;
      std::lock_guard lock(mu);
      got.emplace(n, std::move(s));
      cv.notify_all();
    }));
  const auto deadline = Clock::now() + timeout;
  {
    std::unique_lock lock(mu);
    while (got.size() < names.size() && Clock::now() < deadline) {
      cv.wait_for(lock, ms(20));  // a slice, to see a stop
      if (stop != nullptr) {
        lock.unlock();
        const bool stopped = stop->wait(ms(0));
        lock.lock();
        if (stopped) break;
      }
    }
  }
  subs.clear();  // callbacks done before `got` goes
  std::lock_guard lock(mu);
  return got;
}

// ---- lcmx actions ----

struct ActionsOptions {
  std::vector<std::string> types;
  bool json = false;
  const Globals* g = nullptr;
};
ActionsOptions g_actions;

using SeenAction = SeenServersClients;

int run_actions() {
  const auto& o = g_actions;
  spdlog::set_level(spdlog::level::warn);
  types::TypeRegistry reg;
  try {
    reg = load_types(o.types);
  } catch (const std::exception& e) {
    std::cerr << "lcmx actions: " << e.what() << "\n";
    return 1;
  }
  std::map<std::string, SeenAction> actions;
  std::map<std::string, lcmx_msgs::action_status_t> status;
  try {
    for (const auto& p : observe(*o.g)) {
      for (const auto& e : p.beacon.endpoints) {
        if (e.fingerprint != lcmx_msgs::action_status_t::getHash() || e.topic.size() <= kStatusSuffix.size() ||
            e.topic.compare(e.topic.size() - kStatusSuffix.size(), kStatusSuffix.size(), kStatusSuffix) != 0)
          continue;
        auto& a = actions[e.topic.substr(0, e.topic.size() - kStatusSuffix.size())];
        const SeenEndpoint se = seen_endpoint(p, e);
        (e.kind == lcmx_msgs::endpoint_t::KIND_PUBLISHER ? a.servers : a.clients).push_back(se);
      }
    }
    std::vector<std::string> served;
    for (const auto& [name, a] : actions)
      if (!a.servers.empty()) served.push_back(name);
    if (!served.empty()) {
      auto rt = Runtime::create(runtime_options(*o.g));
      auto node = rt.create_node("lcmx_actions");
      status = read_statuses(node, served, ms(std::max(o.g->wait_ms, 1500)), nullptr);
    }
  } catch (const std::exception& e) {
    std::cerr << "lcmx actions: " << e.what() << "\n";
    return 1;
  }

  if (o.json) {
    std::cout << "{\"actions\":[";
    bool first = true;
    for (const auto& [name, a] : actions) {
      std::cout << (first ? "" : ",") << "{\"name\":" << json_str(name);
      first = false;
      if (auto it = status.find(name); it != status.end()) {
        const auto& s = it->second;
        std::cout << ",\"goal_type\":" << json_str(type_name(reg, s.goal_type, s.goal_fingerprint))
                  << ",\"feedback_type\":" << json_str(type_name(reg, s.feedback_type, s.feedback_fingerprint))
                  << ",\"result_type\":" << json_str(type_name(reg, s.result_type, s.result_fingerprint))
                  << ",\"goals\":[";
        for (std::size_t i = 0; i < s.goals.size(); ++i)
          std::cout << (i ? "," : "") << "{\"id\":" << json_str(s.goals[i].goal_id)
                    << ",\"state\":" << json_str(state_name(s.goals[i].state))
                    << ",\"message\":" << json_str(s.goals[i].message) << "}";
        std::cout << "]";
      }
      print_endpoints_json(std::cout, a);
      std::cout << "}";
    }
    std::cout << "]}" << std::endl;
    return 0;
  }
  if (actions.empty()) {
    std::cout << "no actions seen (listened " << o.g->wait_ms << " ms on " << o.g->url << ")\n";
    return 0;
  }
  for (const auto& [name, a] : actions) {
    std::cout << printable(name);  // names and types from the network: escaped (safe_text.hpp)
    auto it = status.find(name);
    if (it != status.end()) {
      const auto& s = it->second;
      std::cout << "  goal " << printable(type_name(reg, s.goal_type, s.goal_fingerprint)) << ", feedback "
                << printable(type_name(reg, s.feedback_type, s.feedback_fingerprint)) << ", result "
                << printable(type_name(reg, s.result_type, s.result_fingerprint));
    } else if (!a.servers.empty()) {
      std::cout << "  (types unknown: no status heard)";
    }
    std::cout << "\n";
    print_endpoints_text(std::cout, a);
    if (it != status.end())
      for (const auto& gs : it->second.goals)
        std::cout << "  goal " << printable(gs.goal_id) << "  " << state_name(gs.state)
                  << (gs.message.empty() ? "" : "  (" + printable(gs.message) + ")") << "\n";
  }
  return 0;
}

// ---- lcmx action send ----

struct SendOptions {
  std::string name;
  std::optional<std::string> json;
  std::optional<std::string> hex;
  std::vector<std::string> types;
  double timeout_s = 0;  // 0: wait for the end as long as it takes
  double find_s = 5;
  bool json_out = false;
  bool quiet = false;
  const Globals* g = nullptr;
};
SendOptions g_send;

int run_send() {
  const auto& o = g_send;
  spdlog::set_level(spdlog::level::warn);
  types::TypeRegistry reg;
  try {
    reg = load_types(o.types);
  } catch (const std::exception& e) {
    std::cerr << "lcmx action send: " << e.what() << "\n";
    return 1;
  }
  const auto find = std::chrono::duration_cast<ms>(std::chrono::duration<double>(o.find_s));
  try {
    StopSignals stop;
    auto rt = Runtime::create(runtime_options(*o.g));
    auto node = rt.create_node("lcmx_action_send");
    auto client = node.create_action_client_raw(o.name);
    const auto st = read_statuses(node, {o.name}, find, &stop);
    if (stop.stopped()) return 130;
    if (st.empty()) {
      std::cerr << "lcmx action send: no server of action '" << o.name << "' was heard within " << o.find_s
                << " s ('lcmx actions' lists the actions seen)\n";
      return 1;
    }
    const auto& s = st.begin()->second;
    Bytes goal;
    if (s.goal_fingerprint == 0 || o.hex) {
      if (!o.hex) {
        std::cerr << "lcmx action send: action '" << o.name << "' takes raw bytes: give them with --hex\n";
        return 2;
      }
      auto b = from_hex(*o.hex);
      if (!b) {
        std::cerr << "lcmx action send: --hex: not an even number of hex digits\n";
        return 2;
      }
      goal = std::move(*b);
    } else {
      const auto* type = reg.find(static_cast<std::uint64_t>(s.goal_fingerprint));
      if (type == nullptr) {
        std::cerr << "lcmx action send: the server takes goals of " << printable(s.goal_type) << " ("
                  << hex_fingerprint(static_cast<std::uint64_t>(s.goal_fingerprint)) << "), which is not in the type path"
                  << (reg.size() == 0 ? " (give --types DIR|FILE or set LCMX_TYPES_PATH)" : "") << "\n";
        return 1;
      }
      const auto bytes = types::encode(*type, types::from_json(*type, o.json.value_or("{}")));
      goal.resize(bytes.size());
      std::memcpy(goal.data(), bytes.data(), bytes.size());
    }
    const auto* ftype = reg.find(static_cast<std::uint64_t>(s.feedback_fingerprint));
    const auto* rtype = reg.find(static_cast<std::uint64_t>(s.result_fingerprint));
    std::mutex out_mu;
    auto print = [&](const char* what, std::span<const std::byte> b, const types::StructType* t) {
      std::lock_guard lock(out_mu);
      std::string text;
      try {
        if (t != nullptr) {
          const auto v = types::decode(*t, b.data(), b.size());
          text = o.json_out ? types::to_json(v) : types::to_text(v);
        }
      } catch (const std::exception& e) {
        text.clear();
      }
      if (text.empty()) text = o.json_out ? "{\"hex\":\"" + to_hex(b) + "\"}" : to_hex(b) + "\n";
      if (o.json_out) std::cout << "{\"" << what << "\":" << text << "}" << std::endl;
      else std::cout << what << ":\n" << text << std::flush;
    };
    std::function<void(std::span<const std::byte>)> on_feedback;
    if (!o.quiet) on_feedback = [&](std::span<const std::byte> b) { print("feedback", b, ftype); };
    auto sent = client.send_goal(goal, find, on_feedback);
    if (!sent.ok()) {
      std::cerr << "lcmx action send: " << to_string(sent.error()) << ": " << printable(sent.message()) << "\n";
      return 1;
    }
    auto handle = sent.value();
    if (!handle.accepted()) {
      std::cerr << "lcmx action send: goal rejected: " << printable(handle.message()) << "\n";
      return 1;
    }
    {
      std::lock_guard lock(out_mu);
      if (o.json_out) std::cout << "{\"goal\":" << json_str(handle.id()) << ",\"state\":\"accepted\"}" << std::endl;
      else std::cout << "goal " << handle.id() << " accepted\n" << std::flush;
    }
    // Wait for the end in slices, so that Ctrl-C cancels the goal.
    const auto end = o.timeout_s > 0 ? Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                                          std::chrono::duration<double>(o.timeout_s))
                                     : Clock::time_point::max();
    bool canceled = false;
    for (;;) {
      const auto outcome = handle.wait(ms(100));
      if (outcome.ok()) {
        const auto& oc = outcome.value();
        if (oc.result && !oc.result->empty()) print("result", *oc.result, rtype);
        std::lock_guard lock(out_mu);
        if (o.json_out)
          std::cout << "{\"goal\":" << json_str(handle.id()) << ",\"state\":" << json_str(to_string(oc.status.state))
                    << ",\"message\":" << json_str(oc.status.message) << "}" << std::endl;
        else
          std::cout << "goal " << handle.id() << " " << to_string(oc.status.state)
                    << (oc.status.message.empty() ? "" : ": " + printable(oc.status.message)) << "\n" << std::flush;
        if (canceled) return 130;
        return oc.status.state == GoalState::succeeded ? 0 : 1;
      }
      if (outcome.error() != CallErrc::timeout) {
        std::cerr << "lcmx action send: " << to_string(outcome.error()) << ": " << printable(outcome.message()) << "\n";
        return 1;
      }
      if (Clock::now() >= end && !canceled) {
        std::cerr << "lcmx action send: the goal did not end within " << o.timeout_s << " s; canceling it\n";
        canceled = true;  // exit 130 after the cancel: stopped by us
        auto c = handle.cancel(find);
        if (!c.ok()) {
          std::cerr << "lcmx action send: cancel: " << to_string(c.error()) << ": " << printable(c.message()) << "\n";
          return 1;
        }
      }
      if (!canceled && stop.wait(ms(0))) {
        canceled = true;
        {
          std::lock_guard lock(out_mu);
          if (!o.json_out) std::cout << "canceling goal " << handle.id() << "\n" << std::flush;
        }
        auto c = handle.cancel(find);
        if (!c.ok()) {
          std::cerr << "lcmx action send: cancel: " << to_string(c.error()) << ": " << printable(c.message()) << "\n";
          return 1;
        }
      }
    }
  } catch (const std::exception& e) {
    std::cerr << "lcmx action send: " << e.what() << "\n";
    return 1;
  }
}

}  // namespace

Verb add_actions(CLI::App& app, const Globals& g) {
  g_actions.g = &g;
  auto* c = app.add_subcommand("actions", "list the actions discovery sees: types, servers, clients, goals");
  c->add_option("-t,--types", g_actions.types,
                ".lcm file or directory for package-qualified type names (repeatable); default LCMX_TYPES_PATH")
      ->allow_extra_args(false);
  c->add_flag("--json", g_actions.json,
              "one line of JSON: {actions: [{name, goal_type, feedback_type, result_type, goals: [{id, state, "
              "message}], servers: [{participant, host, pid, process, node}], clients: [...]}]}");
  return {c, [] { return run_actions(); }};
}

Verb add_action(CLI::App& app, const Globals& g) {
  g_send.g = &g;
  auto* c = app.add_subcommand("action", "send a goal to an action (lcmx action send)");
  c->require_subcommand(1);
  auto* s = c->add_subcommand("send", "send one goal: the goal as JSON, feedback printed live, then the outcome");
  s->add_option("name", g_send.name, "action name")->required();
  auto* json = s->add_option("json", g_send.json,
                              "the goal as JSON, e.g. '{\"position\": [1, 2, 3]}'; fields not given are zero "
                              "(default {})");
  s->add_option("-t,--types", g_send.types,
                ".lcm file or directory (searched recursively; repeatable, or a ':' list); default LCMX_TYPES_PATH")
      ->allow_extra_args(false);
  s->add_option("--hex", g_send.hex, "the goal as hex bytes (raw actions, or to send exact bytes); not with JSON")
      ->excludes(json);
  s->add_option("--find-timeout", g_send.find_s, "seconds to find the server and get the goal accepted")
      ->check(positive_number())
      ->capture_default_str();
  s->add_option("--timeout", g_send.timeout_s, "cancel the goal if it has not ended after this many seconds (0: never)")
      ->check(non_negative_number())
      ->capture_default_str();
  s->add_flag("--json", g_send.json_out, "JSON lines: {goal, state}, {feedback: ...}, {result: ...}, {goal, state, message}");
  s->add_flag("-q,--quiet", g_send.quiet, "do not print feedback");
  s->footer(
      "Ctrl-C (SIGINT) or SIGTERM cancels the goal and waits for its end. The server's status names its types by "
      "fingerprint; the type path must hold them. Exit: 0 succeeded; 1 rejected, aborted, canceled (by the server), "
      "lost, no server or other error; 2 bad arguments; 130 canceled by Ctrl-C or --timeout.");
  return {c, [] { return run_send(); }};
}

}  // namespace lcmx::cli
