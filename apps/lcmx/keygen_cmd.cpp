// `lcmx keygen --group FILE`: group keys (docs/keyed-groups.md). Writes a new key file, or
// steps an existing one through a rotation: --next adds a second key (accepted, not yet
// sealing), --promote makes it the sealing one, --retire drops the old one. Every write goes
// to a new file renamed over FILE (never through a symbolic link), mode 0600.
#include <iostream>
#include <memory>

#include "lcmx/udpm/error.hpp"
#include "lcmx/udpm/keys.hpp"
#include "verb.hpp"

namespace lcmx::cli {
namespace {

std::string id_hex(std::uint32_t id) {
  char b[16];
  std::snprintf(b, sizeof b, "%08x", id);
  return b;
}

std::string describe_keys(const udpm::GroupKeys& k) {
  std::string s = "seals with key " + id_hex(k.keys[0].id);
  if (k.keys.size() > 1) s += ", also accepts key " + id_hex(k.keys[1].id);
  return s + (k.encrypt ? ", encrypted" : ", authenticated");
}

}  // namespace

Verb add_keygen(CLI::App& app, const Globals&) {
  struct State {
    std::string group;
    bool force = false, encrypt = false, next = false, promote = false, retire = false;
  };
  auto st = std::make_shared<State>();
  auto* c = app.add_subcommand(
      "keygen",
      "write a group key file (--group FILE: a random 32-byte key, mode 0600) for LCMX_VEHICLE_KEY / "
      "LCMX_HOST_KEY, or step one through a rotation (--next, --promote, --retire; docs/keyed-groups.md)");
  c->add_option("--group", st->group, "the key file")->required();
  c->add_flag("--force", st->force, "replace an existing file with a new key");
  c->add_flag("--encrypt", st->encrypt, "mark the file `encrypt`: payloads encrypted, not only authenticated");
  auto* next = c->add_flag("--next", st->next,
                           "rotation step 1: add a new key to FILE, accepted but not yet sealing");
  auto* promote = c->add_flag("--promote", st->promote,
                              "rotation step 2: seal with the second key (the first stays accepted)");
  auto* retire = c->add_flag("--retire", st->retire, "rotation step 3: drop the second (old) key");
  next->excludes(promote)->excludes(retire);
  promote->excludes(retire);
  c->footer(
      "Rotation: do each step on every host before the next step (lcmx re-reads a changed key file "
      "within a second, no restart): --next (copy FILE to every host), --promote (copy), --retire (copy).");
  return {c, [st] {
            try {
              udpm::GroupKeys k;
              const bool step = st->next || st->promote || st->retire;
              if (step) {
                k = udpm::read_key_file(st->group);
                if (st->next) {
                  if (k.keys.size() != 1)
                    throw udpm::Error(udpm::Error::Code::bad_key,
                                      st->group + " already holds two keys: --promote or --retire first");
                  k.keys.push_back(udpm::generate_key());
                } else if (k.keys.size() != 2) {
                  throw udpm::Error(udpm::Error::Code::bad_key, st->group + " holds one key: nothing to " +
                                                                    (st->promote ? "promote" : "retire") +
                                                                    " (--next adds one)");
                } else if (st->promote) {
                  std::swap(k.keys[0], k.keys[1]);
                } else {
                  k.keys.pop_back();
                }
                if (st->encrypt) k.encrypt = true;
              } else {
                k.keys.push_back(udpm::generate_key());
                k.encrypt = st->encrypt;
              }
              udpm::write_key_file(st->group, k, step || st->force);
              std::cout << "wrote " << st->group << " (mode 0600): " << describe_keys(k) << "\n";
            } catch (const std::exception& e) {
              std::cerr << "lcmx keygen: " << e.what() << "\n";
              return 1;
            }
            return 0;
          }};
}

}  // namespace lcmx::cli
