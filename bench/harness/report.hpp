// What a benchmark prints (bench/harness; bench/README.md "The harness"): a Markdown report on
// stdout (and --markdown FILE), progress on stderr, optionally a CSV file (--csv FILE). A report
// is a title, a few lines saying how it was measured (machine_line() first), its tables, then
// "Targets": one line per target, each comparing a figure against a peer measured in the same
// run, ending in **holds**, **FAILS** or "not measured (why)"; then Failures and Notes.
#pragma once

#include <cstddef>
#include <fstream>
#include <functional>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

namespace lcmxbench {

// "1 KB", "6 MB", "1500 B" (exact multiples of 1024 and 1024*1024 only).
std::string size_label(std::size_t bytes);
// A latency cell in µs: one decimal under 100 ("4.3"), none above ("857").
std::string fmt_us(double us);
// A ratio: "1.23x" (`decimals` after the point).
std::string fmt_ratio(double r, int decimals = 2);
// "2026-11-28 01:02:03 UTC, <host>, Linux <release>, <n> CPUs online".
std::string machine_line();

// "**holds**" or "**FAILS**".
inline std::string verdict(bool holds) { return holds ? "**holds**" : "**FAILS**"; }
// A target checked against a peer of the same run: "- <what>: **holds** (0.97x ≤ 1.20x)\n" with
// `ratio` = figure / peer, or "- <what>: not measured\n" when ratio <= 0 (a side is missing).
// `below`: the ratio must be under the limit (else at most the limit).
std::string ratio_target(const std::string& what, double ratio, double limit, bool below = false);

// A Markdown table: header cells, then rows; `align` has one character per column, 'r' for a
// right-aligned one ("---:"), anything else "---".
class Table {
 public:
  explicit Table(std::vector<std::string> header, std::string align = "");
  Table& row(std::vector<std::string> cells);
  std::string markdown() const;  // "| a | b |\n|---|---|\n| 1 | 2 |\n"

 private:
  std::vector<std::string> header_;
  std::string align_;
  std::vector<std::vector<std::string>> rows_;
};

// "\n**<title>**\n- <who>: <text>\n..." for every (who, text); "" when there are none.
std::string list_section(const std::string& title, const std::vector<std::pair<std::string, std::string>>& items);

// A CSV file: the header line, then rows (cells as given: no quoting, the benchmarks write no
// commas in them). Throws std::runtime_error naming the file when it cannot be written.
class Csv {
 public:
  Csv(const std::string& path, const std::string& header);
  template <class... T>
  void row(const T&... cells) {
    std::ostringstream line;
    const char* sep = "";
    ((line << sep << cells, sep = ","), ...);
    f_ << line.str() << "\n";
  }
  void close();  // throws if writing failed

 private:
  std::string path_;
  std::ofstream f_;
};

// Writes `text` to `path`; throws std::runtime_error naming it on failure.
void write_file(const std::string& path, const std::string& text);

// The end of a run: `md` on stdout, and into `markdown_path` unless it is empty; then `more()`
// (if given: the CSV file). Returns false, after saying why on stderr ("<program>: cannot write
// FILE"), when a file could not be written.
bool print_report(const std::string& program, const std::string& md, const std::string& markdown_path,
                  const std::function<void()>& more = {});

// "[<tag>] <text>" on stderr (the progress of a run).
void progress(const std::string& tag, const std::string& text);

}  // namespace lcmxbench
