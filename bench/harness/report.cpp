#include "report.hpp"

#include <sys/utsname.h>
#include <unistd.h>

#include <cstdio>
#include <ctime>
#include <iostream>
#include <stdexcept>

namespace lcmxbench {

std::string size_label(std::size_t bytes) {
  if (bytes >= (1u << 20) && bytes % (1u << 20) == 0) return std::to_string(bytes >> 20) + " MB";
  if (bytes >= 1024 && bytes % 1024 == 0) return std::to_string(bytes >> 10) + " KB";
  return std::to_string(bytes) + " B";
}

std::string fmt_us(double us) {
  char b[32];
  std::snprintf(b, sizeof b, us < 100 ? "%.1f" : "%.0f", us);
  return b;
}

std::string fmt_ratio(double r, int decimals) {
  char b[32];
  std::snprintf(b, sizeof b, "%.*fx", decimals, r);
  return b;
}

std::string machine_line() {
  char date[64];
  const std::time_t now = std::time(nullptr);
  std::strftime(date, sizeof date, "%Y-%m-%d %H:%M:%S %Z", std::localtime(&now));
  utsname u{};
  ::uname(&u);
  return std::string(date) + ", " + u.nodename + ", Linux " + u.release + ", " +
         std::to_string(::sysconf(_SC_NPROCESSORS_ONLN)) + " CPUs online";
}

std::string ratio_target(const std::string& what, double ratio, double limit, bool below) {
  if (ratio <= 0) return "- " + what + ": not measured\n";
  const bool ok = below ? ratio < limit : ratio <= limit;
  char b[96];
  std::snprintf(b, sizeof b, " (%.2fx %s %.2gx)\n", ratio, ok ? (below ? "<" : "≤") : (below ? "≥" : ">"), limit);
  return "- " + what + ": " + verdict(ok) + b;
}

Table::Table(std::vector<std::string> header, std::string align) : header_(std::move(header)), align_(std::move(align)) {}

Table& Table::row(std::vector<std::string> cells) {
  rows_.push_back(std::move(cells));
  return *this;
}

std::string Table::markdown() const {
  std::string out = "|";
  for (const auto& h : header_) out += " " + h + " |";
  out += "\n|";
  for (std::size_t i = 0; i < header_.size(); ++i) out += i < align_.size() && align_[i] == 'r' ? "---:|" : "---|";
  out += "\n";
  for (const auto& r : rows_) {
    out += "|";
    for (const auto& c : r) out += " " + c + " |";
    out += "\n";
  }
  return out;
}

std::string list_section(const std::string& title, const std::vector<std::pair<std::string, std::string>>& items) {
  if (items.empty()) return "";
  std::string out = "\n**" + title + "**\n";
  for (const auto& [who, text] : items) out += "- " + who + ": " + text + "\n";
  return out;
}

Csv::Csv(const std::string& path, const std::string& header) : path_(path), f_(path) {
  f_ << header << "\n";
  if (!f_) throw std::runtime_error("cannot write " + path);
}

void Csv::close() {
  f_.close();
  if (!f_) throw std::runtime_error("cannot write " + path_);
}

void write_file(const std::string& path, const std::string& text) {
  std::ofstream f(path);
  f << text;
  f.close();
  if (!f) throw std::runtime_error("cannot write " + path);
}

bool print_report(const std::string& program, const std::string& md, const std::string& markdown_path,
                  const std::function<void()>& more) {
  std::cout << md << std::flush;
  try {
    if (!markdown_path.empty()) write_file(markdown_path, md);
    if (more) more();
  } catch (const std::exception& e) {
    std::cerr << program << ": " << e.what() << "\n";
    return false;
  }
  return true;
}

void progress(const std::string& tag, const std::string& text) { std::cerr << "[" << tag << "] " << text << std::endl; }

}  // namespace lcmxbench
