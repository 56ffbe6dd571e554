// _Runtime and _Node (python/lcmx/__init__.py's Runtime and Node): the process's runtime, its
// events, its nodes and a manual node's spin_once. The nodes' factories of endpoints, services
// and actions are bound by their parts (pubsub.cpp, services.cpp, actions.cpp).
#include "binding.hpp"

namespace lcmxpy {

NodeClass bind_runtime(py::module_& m) {
  py::class_<PyRuntime, std::shared_ptr<PyRuntime>>(m, "_Runtime")
      .def(py::init([](std::optional<std::string> discovery_url, std::optional<std::string> vehicle_url,
                       std::optional<bool> mirror, std::optional<int> beacon_period_ms,
                       std::optional<int> lease_ms) {
             auto o = lcmx::RuntimeOptions::from_env();
             if (discovery_url) o.discovery_url = *discovery_url;
             if (vehicle_url) o.vehicle_url = *vehicle_url;
             if (mirror) o.mirror = *mirror;
             if (beacon_period_ms) o.beacon_period = std::chrono::milliseconds(*beacon_period_ms);
             if (lease_ms) o.lease = std::chrono::milliseconds(*lease_ms);
             auto r = std::make_shared<PyRuntime>();
             {
               py::gil_scoped_release nogil;
               r->rt.emplace(lcmx::Runtime::create(std::move(o)));
             }
             register_closable(r);
             g_runtime = r;
             return r;
           }),
           py::arg("discovery_url") = py::none(), py::arg("vehicle_url") = py::none(),
           py::arg("mirror") = py::none(), py::arg("beacon_period_ms") = py::none(),
           py::arg("lease_ms") = py::none())
      .def("close", &PyRuntime::close)
      .def_property_readonly("closed", [](PyRuntime& r) { return !r.rt.has_value(); })
      .def_property_readonly("participant_id", [](PyRuntime& r) { return r.get().participant_id(); })
      .def_property_readonly("host_id", [](PyRuntime& r) { return r.get().host_id(); })
      .def("on_event",
           [](PyRuntime& r, py::object cb) {
             auto box = r.events;
             box->fn = std::move(cb);
             r.get().on_event([box](const lcmx::Event& e) {
               if (g_exiting.load()) return;
               ExecutorGil gil;
               if (!box->fn || box->fn.is_none()) return;
               try {
                 box->fn(lcmx::to_string(e.kind), e.channel, e.message);
               } catch (py::error_already_set& err) {
                 report_callback_error(*box, "on_event", err);
               }
             });
           })
      .def("create_node", [](const std::shared_ptr<PyRuntime>& r, std::string name, bool manual, int threads) {
        lcmx::NodeOptions o;
        o.executor.kind = manual ? lcmx::ExecutorKind::manual : lcmx::ExecutorKind::own_threads;
        o.executor.threads = threads;
        auto n = std::make_shared<PyNode>();
        n->runtime = r;
        n->node = std::make_shared<lcmx::Node>(r->get().create_node(std::move(name), o));
        r->adopt(n);
        return n;
      }, py::arg("name"), py::arg("manual") = false, py::arg("threads") = 1);

  NodeClass node(m, "_Node");
  node.def("close", &PyNode::close)
      .def_property_readonly("name", [](PyNode& n) { return n.get()->name(); })
      .def("spin_once",
           [](PyNode& n, std::optional<double> timeout) {
             std::size_t ran = 0;
             wait_on(n.get(), timeout, [&ran](lcmx::Node& node, std::chrono::nanoseconds slice) {
               ran = node.spin_once(slice);
               return ran > 0;
             });
             return ran;
           },
           py::arg("timeout") = py::none());
  return node;
}

}  // namespace lcmxpy
