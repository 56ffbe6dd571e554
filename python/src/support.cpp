// The handle registry, the buffer exporter behind SlotView, and what every part of the binding
// shares (binding.hpp).
#include <mutex>

#include "binding.hpp"

namespace lcmxpy {
namespace {

std::mutex g_registry_mu;
std::list<std::weak_ptr<Closable>> g_registry;  // creation order

int slot_getbuffer(PyObject* self, Py_buffer* view, int flags) {
  auto* b = reinterpret_cast<SlotBuffer*>(self);
  if (!b->ptr) {
    PyErr_SetString(PyExc_ValueError,
                    "lcmx: this memory is no longer valid (its callback returned, or its loan was published)");
    view->obj = nullptr;
    return -1;
  }
  if (PyBuffer_FillInfo(view, self, b->ptr, b->len, b->readonly, flags) < 0) return -1;
  ++b->exports;
  return 0;
}

void slot_releasebuffer(PyObject* self, Py_buffer*) { --reinterpret_cast<SlotBuffer*>(self)->exports; }

}  // namespace

PyTypeObject* slot_buffer_type() {  // GIL
  static PyTypeObject* type = [] {
    static PyType_Slot slots[] = {{Py_bf_getbuffer, reinterpret_cast<void*>(slot_getbuffer)},
                                  {Py_bf_releasebuffer, reinterpret_cast<void*>(slot_releasebuffer)},
                                  {0, nullptr}};
    static PyType_Spec spec = {"lcmx._lcmx._SlotBuffer", sizeof(SlotBuffer), 0, Py_TPFLAGS_DEFAULT, slots};
    auto* t = reinterpret_cast<PyTypeObject*>(PyType_FromSpec(&spec));
    if (!t) throw py::error_already_set();
    return t;
  }();
  return type;
}

void register_closable(const std::shared_ptr<Closable>& c) {
  std::lock_guard lock(g_registry_mu);
  for (auto it = g_registry.begin(); it != g_registry.end();)
    it = it->expired() ? g_registry.erase(it) : std::next(it);
  g_registry.push_back(c);
}

void close_all() {
  g_exiting.store(true);
  std::vector<std::shared_ptr<Closable>> live;
  {
    std::lock_guard lock(g_registry_mu);
    for (auto it = g_registry.rbegin(); it != g_registry.rend(); ++it)
      if (auto c = it->lock()) live.push_back(std::move(c));
    g_registry.clear();
  }
  for (auto& c : live) c->close();
}

void report_callback_error(CallbackBox& box, const std::string& where, py::error_already_set& e) {
  const auto n = box.errors.fetch_add(1) + 1;
  spdlog::error("lcmx: python callback on '{}' raised ({} so far): {}", where, n, e.what());
}

std::chrono::milliseconds to_ms(double seconds) {
  if (!(seconds >= 0.0)) throw lcmx::Error(lcmx::Errc::invalid_argument, "a timeout must be >= 0 seconds");
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::duration<double>(seconds));
}

py::object decode_or_bad_request(const py::object& decode, py::object& view, const std::string& type_name) {
  try {
    return decode(view);
  } catch (py::error_already_set& e) {
    throw lcmx::detail::BadRequest("the payload did not decode as " + type_name + ": " + e.what());
  }
}

}  // namespace lcmxpy
