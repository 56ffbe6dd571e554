// `lcmx graph`: the system as a graph (graph_model.hpp) in DOT on stdout or in a file, SVG/PNG
// through Graphviz's `dot`, or JSON. `--watch` keeps observing and rewrites the file (through a
// temporary file and rename, so readers never see half a file) whenever the structure changes,
// checked every 250 ms, until SIGINT/SIGTERM or --duration.
// Threads: the main thread only (plus the observer's discovery threads).
#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <spdlog/spdlog.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iostream>
#include <optional>
#include <thread>

#include "graph_model.hpp"
#include "monitor_cmds.hpp"
#include "tools_common.hpp"

extern char** environ;

namespace lcmx::cli {
namespace {

struct GraphOptions {
  std::string output;
  std::string format;  // dot, svg, png, json; default from the output's extension, else dot
  bool json = false;
  bool watch = false;
  double duration_s = 0;
  std::vector<std::string> types;
  const Globals* g = nullptr;
};
GraphOptions g_graph;

std::atomic<bool> g_graph_stop{false};
extern "C" void on_graph_signal(int) { g_graph_stop.store(true); }

std::optional<std::string> find_in_path(const std::string& prog) {
  const char* path = std::getenv("PATH");
  std::string p = path ? path : "/usr/bin:/bin";
  std::size_t start = 0;
  while (start <= p.size()) {
    const auto end = p.find(':', start);
    std::string dir = p.substr(start, end == std::string::npos ? std::string::npos : end - start);
    if (dir.empty()) dir = ".";
    const std::string f = dir + "/" + prog;
    if (::access(f.c_str(), X_OK) == 0) return f;
    if (end == std::string::npos) break;
    start = end + 1;
  }
  return std::nullopt;
}

// Writes `text` to `file` atomically (temporary + rename). Throws std::runtime_error.
void write_file(const std::string& file, const std::string& text) {
  const std::string tmp = file + ".tmp" + std::to_string(::getpid());
  {
    std::ofstream f(tmp, std::ios::binary | std::ios::trunc);
    f << text;
    f.close();
    if (!f) {
      ::unlink(tmp.c_str());
      throw std::runtime_error("cannot write '" + tmp + "': " + std::strerror(errno));
    }
  }
  if (::rename(tmp.c_str(), file.c_str()) != 0) {
    const int e = errno;
    ::unlink(tmp.c_str());
    throw std::runtime_error("cannot rename to '" + file + "': " + std::strerror(e));
  }
}

// Runs `dot -T<format>` on `text` into `file` (temporary + rename). Throws std::runtime_error.
void render(const std::string& dot, const std::string& format, const std::string& text, const std::string& file) {
  const std::string tmp = file + ".tmp" + std::to_string(::getpid());
  int in[2];
  if (::pipe2(in, O_CLOEXEC) != 0) throw std::runtime_error(std::string("pipe: ") + std::strerror(errno));
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  posix_spawn_file_actions_adddup2(&fa, in[0], STDIN_FILENO);
  const std::string t = "-T" + format;
  const std::string out = "-o" + tmp;
  std::vector<char*> args{const_cast<char*>(dot.c_str()), const_cast<char*>(t.c_str()),
                          const_cast<char*>(out.c_str()), nullptr};
  pid_t pid = -1;
  const int rc = ::posix_spawn(&pid, dot.c_str(), &fa, nullptr, args.data(), environ);
  posix_spawn_file_actions_destroy(&fa);
  ::close(in[0]);
  if (rc != 0) {
    ::close(in[1]);
    throw std::runtime_error("cannot run '" + dot + "': " + std::strerror(rc));
  }
  // SIGPIPE if dot dies early: ignored here, write() then fails and dot's status says why.
  ::signal(SIGPIPE, SIG_IGN);
  std::size_t done = 0;
  while (done < text.size()) {
    const ssize_t n = ::write(in[1], text.data() + done, text.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    done += static_cast<std::size_t>(n);
  }
  ::close(in[1]);
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    ::unlink(tmp.c_str());
    throw std::runtime_error("'" + dot + " " + t + "' failed (exit status " +
                             std::to_string(WIFEXITED(status) ? WEXITSTATUS(status) : -1) + ")");
  }
  if (::rename(tmp.c_str(), file.c_str()) != 0) {
    const int e = errno;
    ::unlink(tmp.c_str());
    throw std::runtime_error("cannot rename to '" + file + "': " + std::strerror(e));
  }
}

std::string extension(const std::string& f) {
  const auto slash = f.rfind('/');
  const auto dot = f.rfind('.');
  if (dot == std::string::npos || (slash != std::string::npos && dot < slash)) return "";
  std::string e = f.substr(dot + 1);
  for (auto& c : e) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return e;
}

int run_graph() {
  const auto& o = g_graph;
  spdlog::set_level(spdlog::level::warn);
  std::string format = o.json ? "json" : o.format;
  if (format.empty()) {
    const std::string e = extension(o.output);
    if (e == "svg" || e == "png" || e == "pdf" || e == "json") {
      format = e;
    } else if (e.empty() || e == "dot" || e == "gv") {
      format = "dot";
    } else {
      std::cerr << "lcmx graph: -o " << o.output << ": no format for '." << e
                << "': use .dot .svg .png .pdf .json, or say which with --format\n";
      return 2;
    }
  }
  if (o.json && !o.format.empty() && o.format != "json") {
    std::cerr << "lcmx graph: --json and --format " << o.format << " exclude each other\n";
    return 2;
  }
  if (o.watch && o.output.empty()) {
    std::cerr << "lcmx graph: --watch rewrites a file: give -o FILE\n";
    return 2;
  }
  const bool graphviz = format == "svg" || format == "png" || format == "pdf";
  if (graphviz && o.output.empty()) {
    std::cerr << "lcmx graph: --format " << format << " needs -o FILE (binary output is not written to a terminal)\n";
    return 2;
  }
  std::string dot;
  if (graphviz) {
    const auto d = find_in_path("dot");
    if (!d) {
      std::cerr << "lcmx graph: " << format << " output needs Graphviz's 'dot', not found in PATH (Debian: "
                << "apt-get install graphviz); DOT text is written with -o FILE.dot or --format dot\n";
      return 1;
    }
    dot = *d;
  }

  types::TypeRegistry registry;
  try {
    const auto paths = types::TypeRegistry::paths_or_env(o.types);
    if (!paths.empty()) registry = types::TypeRegistry::load(paths);
  } catch (const types::Error& e) {
    std::cerr << "lcmx graph: type path: " << e.what() << "\n";
    return 2;
  }

  struct sigaction sa{};
  sa.sa_handler = on_graph_signal;
  sigemptyset(&sa.sa_mask);
  ::sigaction(SIGINT, &sa, nullptr);
  ::sigaction(SIGTERM, &sa, nullptr);

  std::optional<Observer> obs;
  try {
    obs.emplace(*o.g);
  } catch (const std::exception& e) {
    std::cerr << "lcmx graph: " << e.what() << "\n";
    return 1;
  }
  auto text_of = [&](const std::vector<discovery::Participant>& ps) {
    return format == "json" ? graph::to_json(ps, &registry) + "\n" : graph::to_dot(ps, &registry);
  };
  auto emit = [&](const std::string& text) {
    if (o.output.empty()) {
      std::cout << text << std::flush;
    } else if (graphviz) {
      render(dot, format, text, o.output);
    } else {
      write_file(o.output, text);
    }
  };

  using Clock = std::chrono::steady_clock;
  const auto start = Clock::now();
  // A listening window, a query (participants answer at once), the rest of the window.
  const auto first = start + std::chrono::milliseconds(o.g->wait_ms);
  std::this_thread::sleep_for(std::chrono::milliseconds(o.g->wait_ms / 2));
  obs->query();
  while (Clock::now() < first && !g_graph_stop.load()) std::this_thread::sleep_for(std::chrono::milliseconds(20));
  // The structure without counters, to notice changes (a DOT of the sorted participants).
  std::string last_structure;
  try {
    auto ps = obs->participants();
    last_structure = graph::to_dot(ps);
    emit(text_of(ps));
    if (!o.output.empty()) std::cerr << "lcmx graph: wrote " << o.output << " (" << ps.size() << " participants)\n";
    if (!o.watch) return 0;
    while (!g_graph_stop.load()) {
      std::this_thread::sleep_for(std::chrono::milliseconds(250));
      if (o.duration_s > 0 && Clock::now() - start >= std::chrono::duration<double>(o.duration_s)) break;
      ps = obs->participants();
      auto structure = graph::to_dot(ps);
      if (structure == last_structure) continue;
      last_structure = std::move(structure);
      emit(text_of(ps));
      std::cerr << "lcmx graph: wrote " << o.output << " (" << ps.size() << " participants)\n";
    }
  } catch (const std::exception& e) {
    std::cerr << "lcmx graph: " << e.what() << "\n";
    return 1;
  }
  return 0;
}

}  // namespace

Verb add_graph(CLI::App& app, const Globals& g) {
  g_graph.g = &g;
  auto* c = app.add_subcommand(
      "graph",
      "the system as a graph: hosts -> processes -> nodes -> topics, with the path of each "
      "publisher/subscriber pair; DOT, SVG/PNG (Graphviz) or JSON");
  c->add_option("-o,--output", g_graph.output,
                "write to FILE (default: stdout); its extension (.dot .svg .png .pdf .json; none: DOT) picks the "
                "format, unless --format says");
  c->add_option("--format", g_graph.format, "dot, svg, png, pdf (through Graphviz's dot) or json")
      ->check(CLI::IsMember({"dot", "svg", "png", "pdf", "json"}));
  c->add_flag("--json", g_graph.json, "JSON instead of DOT (same as --format json)");
  c->add_flag("--watch", g_graph.watch,
              "keep observing and rewrite FILE whenever the topology changes (until SIGINT/SIGTERM)");
  c->add_option("--duration", g_graph.duration_s, "with --watch: stop after this many seconds (0: until SIGINT)")
      ->check(non_negative_number());
  c->add_option("--types", g_graph.types,
                "'.lcm' files or directories for package-qualified type names (by fingerprint); "
                "default LCMX_TYPES_PATH")
      ->type_name("PATH")
      ->allow_extra_args(false);  // one value per --types (repeatable), as the other verbs
  c->footer("Examples: lcmx graph | dot -Tsvg > g.svg;  lcmx graph -o g.png;  lcmx graph --watch -o live.svg");
  return {c, [] { return run_graph(); }};
}

}  // namespace lcmx::cli
