// Helpers of `lcmx monitor` and `lcmx graph`: a discovery observer over the host-local group
// and, when given, the vehicle group (as `lcmx topics` uses), kept open while the tool runs.
// Threads: participants() and query() from any thread. Errors: the constructor throws what
// Discovery throws when a group cannot be opened.
#pragma once

#include <memory>
#include <set>
#include <string>
#include <vector>

#include "lcmx/discovery/discovery.hpp"
#include "lcmx/udpm/udpm.hpp"
#include "verb.hpp"

namespace lcmx::cli {

// The discovery options of a tool's observer of the host-local group or (`vehicle`) the
// vehicle group. The vehicle group's observer is of the vehicle scope: no registry of its own
// (a host-scope one would open a registry for the vehicle group and take this host's speaker
// for a twin). Throws what observer_group throws.
inline discovery::Options observer_options(const Globals& g, bool vehicle) {
  discovery::Options o;
  o.group = observer_group(g, vehicle);
  o.observer = true;
  o.scope = vehicle ? lcmx_msgs::beacon_t::SCOPE_VEHICLE : lcmx_msgs::beacon_t::SCOPE_HOST;
  return o;
}

class Observer {
 public:
  explicit Observer(const Globals& g) {
    for (const bool vehicle : {false, true}) {
      if (vehicle && g.vehicle_url.empty()) continue;
      d_.push_back(std::make_unique<discovery::Discovery>(observer_options(g, vehicle), nullptr, nullptr));
    }
  }
  // Asks every participant to beacon now.
  void query() {
    for (auto& d : d_) d->query();
  }
  // Participants known now; one seen in both scopes once, from its host-local beacon.
  std::vector<discovery::Participant> participants() const {
    std::vector<discovery::Participant> all;
    std::set<std::int64_t> seen;
    for (const auto& d : d_)
      for (auto& p : d->participants())
        if (seen.insert(p.beacon.participant_id).second) all.push_back(std::move(p));
    return all;
  }

 private:
  std::vector<std::unique_ptr<discovery::Discovery>> d_;
};

}  // namespace lcmx::cli
