// RAII for Cyclone DDS entities (dds_entity_t) and the one error type of lcmx::dds's DDS calls.
#pragma once

#include <dds/dds.h>

#include <stdexcept>
#include <string>
#include <utility>

namespace lcmx::dds {

// A Cyclone DDS call failed. what(): "<what>: <dds_strretcode>".
class DdsError : public std::runtime_error {
 public:
  DdsError(const std::string& what, dds_return_t rc)
      : std::runtime_error(what + ": " + dds_strretcode(rc)), rc_(rc) {}
  dds_return_t code() const noexcept { return rc_; }

 private:
  dds_return_t rc_;
};

// Returns rc when it is not an error (>= 0: an entity or DDS_RETCODE_OK); throws DdsError.
inline dds_return_t check(dds_return_t rc, const std::string& what) {
  if (rc < 0) throw DdsError(what, rc);
  return rc;
}

// Owns one entity: dds_delete() on destruction (which deletes its children too and waits for
// its listeners' running callbacks). Move-only. An empty Entity holds 0.
class Entity {
 public:
  Entity() = default;
  // Takes `e`, the result of a dds_create_*; throws DdsError (what) if it is an error code.
  Entity(dds_entity_t e, const std::string& what) : e_(check(e, what)) {}
  Entity(Entity&& o) noexcept : e_(std::exchange(o.e_, 0)) {}
  Entity& operator=(Entity&& o) noexcept {
    if (this != &o) {
      reset();
      e_ = std::exchange(o.e_, 0);
    }
    return *this;
  }
  Entity(const Entity&) = delete;
  Entity& operator=(const Entity&) = delete;
  ~Entity() { reset(); }

  dds_entity_t get() const noexcept { return e_; }
  explicit operator bool() const noexcept { return e_ > 0; }
  void reset() noexcept {
    if (e_ > 0) dds_delete(e_);
    e_ = 0;
  }

 private:
  dds_entity_t e_ = 0;
};

// Owns a dds_qos_t.
class Qos {
 public:
  Qos() : q_(dds_create_qos()) {}
  Qos(const Qos&) = delete;
  Qos& operator=(const Qos&) = delete;
  ~Qos() { dds_delete_qos(q_); }
  dds_qos_t* get() const noexcept { return q_; }

 private:
  dds_qos_t* q_;
};

}  // namespace lcmx::dds
