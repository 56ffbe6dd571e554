// lcmx._lcmx: the pybind11 module under the `lcmx` Python package (python/lcmx/__init__.py).
// One file per part of the API it binds; binding.hpp lists them, with the threading and
// ownership rules they share.
#include "binding.hpp"

using namespace lcmxpy;

PYBIND11_MODULE(_lcmx, m) {
  m.doc() = "lcmx: LCM-compatible robotics middleware (C++ core); see the lcmx package.";

  static py::exception<lcmx::Error> error(m, "Error", PyExc_RuntimeError);
  py::register_exception_translator([](std::exception_ptr p) {
    try {
      if (p) std::rethrow_exception(p);
    } catch (const lcmx::Error& e) {
      error(e.what());
    }
  });

  NodeClass node = bind_runtime(m);
  bind_services(m, node);
  bind_actions(m, node);
  bind_pubsub(m, node);
  bind_lcm(m);

  m.def("_current_runtime", []() -> std::shared_ptr<PyRuntime> {
    auto r = g_runtime.lock();
    return r && r->rt ? r : nullptr;
  });
  m.def("_close_all", &close_all);
}
