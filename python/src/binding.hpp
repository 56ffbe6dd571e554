// The private face of the lcmx._lcmx pybind11 module (python/src/): what every file of the
// binding shares. Each file binds one part of the API and owns its handles:
//   module.cpp    the module: lcmx.Error, _current_runtime, _close_all (atexit)
//   support.cpp   the handle registry (close_all), exported memory (SlotView), callback errors
//   runtime.cpp   _Runtime and _Node (create_node, on_event, spin_once)
//   pubsub.cpp    _Publisher, Loan, _Subscriber (Node.advertise_raw, Node.subscribe_raw)
//   services.cpp  _Service, _Client (Node.create_service_raw, Node.create_client_raw)
//   actions.cpp   _ActionServer, _ActionGoal, _ActionClient, _ClientGoal (Node.create_action_*_raw)
//   lcm.cpp       _LCM, LCMSubscription: the C++ half of the LCM drop-in (lcmx.LCM)
// The Python API is python/lcmx/__init__.py over these names.
//
// Threads and the GIL:
//  - Callbacks run on the node's executor thread (or inside spin_once() for a manual node);
//    the GIL is taken only around the call into Python.
//  - Every call that may wait for an executor (closing a subscriber, node or runtime,
//    spin_once, publish, waits) releases the GIL first, so a callback waiting for the GIL
//    never deadlocks with the thread that waits for it.
//  - Python objects held by C++ callbacks (CallbackBox) are released under the GIL by
//    close(); at interpreter exit an atexit hook closes every live handle before Python
//    finalises, and executor threads never touch Python after that (g_exiting).
// Ownership: each Python handle owns its C++ handle (a shared_ptr: a call that releases the
// GIL holds its own reference). The runtime keeps every node, endpoint, service, client and
// LCM made from it until they or it are closed (close(), the context manager, or the atexit
// hook), so dropping a Python handle does not unsubscribe. A node keeps its runtime alive.
#pragma once

#include <pybind11/functional.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <list>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include <spdlog/spdlog.h>

#include "lcmx/core/runtime.hpp"

namespace lcmxpy {

namespace py = pybind11;
using namespace std::chrono_literals;

// Set by close_all() (the atexit hook): from then on lcmx threads never enter Python.
inline std::atomic<bool> g_exiting{false};

// Anything a Python handle owns in C++ that must be dropped before the interpreter ends.
struct Closable {
  virtual ~Closable() = default;
  // Called with the GIL held; releases it while waiting for lcmx threads.
  virtual void close() = 0;
  virtual bool closed() const = 0;
};

// Registers a handle for close_all() (creation order). GIL held.
void register_closable(const std::shared_ptr<Closable>& c);
// atexit: closes every live handle, newest first (subscribers before nodes before runtimes).
void close_all();

// A Python callable used from lcmx threads. `fn` is read and cleared under the GIL only.
struct CallbackBox {
  py::object fn;
  py::object decode;  // typed subscribers: the lcm-gen class's decode (or None)
  std::atomic<std::uint64_t> errors{0};
  ~CallbackBox() {
    // Normally cleared by close() under the GIL; otherwise never touch Python without it.
    if ((fn || decode) && Py_IsInitialized() && !g_exiting.load()) {
      py::gil_scoped_acquire gil;
      fn = py::object();
      decode = py::object();
    } else {
      fn.release();
      decode.release();
    }
  }
  void clear() {  // GIL held
    fn = py::object();
    decode = py::object();
  }
};

// The GIL for a callback on a long-lived lcmx thread (a node's executor, a client's or the
// discovery thread): such a thread keeps the Python thread state pybind11 made for it between
// callbacks (inc_ref) instead of creating and deleting one per callback, which cost several µs
// of each small message's latency (bench/python). It is deleted when the thread ends (the
// thread-local below), unless the interpreter is exiting then. Threads Python made (a manual
// node's spin_once caller) have their own state and are left alone. Per-goal execute threads
// take py::gil_scoped_acquire.
struct KeptThreadState {
  PyThreadState* state = nullptr;
  ~KeptThreadState() {  // at the thread's exit, without the GIL
    if (!state || g_exiting.load() || !Py_IsInitialized()) return;
    PyEval_RestoreThread(state);
    PyThreadState_Clear(state);
    PyThreadState_DeleteCurrent();  // and releases the GIL
  }
};

class ExecutorGil {
 public:
  ExecutorGil() {
    thread_local KeptThreadState kept;
    if (!kept.state && foreign_) {
      gil_.inc_ref();
      kept.state = PyThreadState_Get();
    }
  }

 private:
  bool foreign_ = PyGILState_GetThisThreadState() == nullptr;  // before gil_ (declaration order)
  py::gil_scoped_acquire gil_;
};

// Counts and logs an exception a Python callback raised on an lcmx thread (GIL held).
void report_callback_error(CallbackBox& box, const std::string& where, py::error_already_set& e);

// The memory behind the memoryviews lcmx hands out (a received message, a loaned slot):
// a buffer exporter that counts its exports. A memoryview and every slice or cast of it hold
// one export between them, and numpy arrays over them keep it too, so once our own view is
// released, exports > 0 means something still refers to the memory; revoke() then makes new
// exports fail.
struct SlotBuffer {
  PyObject_HEAD
  char* ptr;
  Py_ssize_t len;
  int readonly;
  Py_ssize_t exports;
};

// The Python type of SlotBuffer (support.cpp), made on first use. GIL held.
PyTypeObject* slot_buffer_type();

// A memoryview of [data, data + size) (writable unless readonly) and its exporter. GIL held.
struct SlotView {
  py::object exporter, view;
  SlotView(const void* data, std::size_t size, bool readonly) {
    auto* type = slot_buffer_type();
    exporter = py::reinterpret_steal<py::object>(type->tp_alloc(type, 0));
    if (!exporter) throw py::error_already_set();
    auto* b = reinterpret_cast<SlotBuffer*>(exporter.ptr());
    b->ptr = static_cast<char*>(const_cast<void*>(data));
    b->len = static_cast<Py_ssize_t>(size);
    b->readonly = readonly ? 1 : 0;
    view = py::reinterpret_steal<py::object>(PyMemoryView_FromObject(exporter.ptr()));
    if (!view) throw py::error_already_set();
  }
  // view.release(): false (the error cleared) if it is exported (an array over it). On the
  // path of every message: no attribute lookup by string.
  bool release_view() {
    static PyObject* name = PyUnicode_InternFromString("release");
    PyObject* r = PyObject_CallMethodNoArgs(view.ptr(), name);
    if (!r) {
      PyErr_Clear();
      return false;
    }
    Py_DECREF(r);
    return true;
  }
  // Releases our view and revokes the memory; false if something still refers to it (a
  // slice, a cast, an array over it), which cannot be revoked.
  bool revoke() {
    bool clean = true;
    if (view) {
      clean = release_view();
      view = py::object();
    }
    if (exporter) {
      auto* b = reinterpret_cast<SlotBuffer*>(exporter.ptr());
      if (b->exports > 0) clean = false;
      b->ptr = nullptr;
    }
    return clean;
  }
  // Releases our view if nothing else refers to the memory (then true), else leaves it all.
  bool try_release() {
    if (!exporter) return true;
    if (view && !release_view()) return false;
    view = py::object();
    return reinterpret_cast<SlotBuffer*>(exporter.ptr())->exports == 0;
  }
};

// Runs `fn` with a read-only memoryview over `data`, revoked after the call (so a view kept
// past the callback raises instead of reading reused memory; slices, casts and arrays over it
// that are kept cannot be revoked: logged). GIL held.
template <class F>
void with_view(std::span<const std::byte> data, F&& fn) {
  SlotView slot(data.data(), data.size(), true);
  try {
    fn(slot.view);
  } catch (...) {
    slot.revoke();
    throw;
  }
  if (!slot.revoke())
    spdlog::warn("lcmx: a view of a received message (a slice, cast or array of its memoryview) was kept past "
                 "its callback; it reads memory that lcmx reuses");
}

// Waits in slices so Ctrl-C (SIGINT) raises KeyboardInterrupt promptly. `step` is called
// without the GIL with the slice's timeout and returns true when done.
template <class Step>
bool wait_interruptible(std::optional<double> timeout_s, Step&& step) {
  const auto deadline = timeout_s ? std::chrono::steady_clock::now() +
                                        std::chrono::duration_cast<std::chrono::nanoseconds>(
                                            std::chrono::duration<double>(std::max(0.0, *timeout_s)))
                                  : std::chrono::steady_clock::time_point::max();
  for (;;) {
    auto slice = std::chrono::nanoseconds(100ms);
    const auto now = std::chrono::steady_clock::now();
    if (timeout_s) slice = std::min(slice, std::chrono::nanoseconds(std::max(deadline - now, 0ns)));
    bool done;
    {
      py::gil_scoped_release nogil;
      done = step(slice);
    }
    if (done) return true;
    if (PyErr_CheckSignals() != 0) throw py::error_already_set();
    if (std::chrono::steady_clock::now() >= deadline) return false;
  }
}

// ---- handles ----
// Handles are held by shared_ptr: a call that releases the GIL works on its own reference, so
// close() from another thread meanwhile cannot free what it uses; the last reference is then
// dropped without the GIL (drop()).
template <class H>
void drop(std::shared_ptr<H>& h) {
  if (!h) return;
  py::gil_scoped_release nogil;
  h.reset();
}

// wait_interruptible over a handle of our own (h: a copy of the Python handle's shared_ptr),
// dropped without the GIL however the wait ends. step(H&, slice) -> bool (done).
template <class H, class Step>
bool wait_on(std::shared_ptr<H> h, std::optional<double> timeout_s, Step&& step) {
  bool ok = false;
  try {
    ok = wait_interruptible(timeout_s, [&](std::chrono::nanoseconds slice) { return step(*h, slice); });
  } catch (...) {
    drop(h);
    throw;
  }
  drop(h);
  return ok;
}

inline std::chrono::milliseconds slice_ms(std::chrono::nanoseconds slice) {
  return std::max(std::chrono::duration_cast<std::chrono::milliseconds>(slice), std::chrono::milliseconds(1));
}

// Seconds from Python as a timeout; throws lcmx::Error (invalid_argument) below 0 or NaN.
std::chrono::milliseconds to_ms(double seconds);

inline py::bytes to_bytes(std::span<const std::byte> b) {
  return py::bytes(reinterpret_cast<const char*>(b.data()), b.size());
}

inline std::span<const std::byte> buffer_bytes(const py::buffer_info& info) {
  return {static_cast<const std::byte*>(info.ptr), static_cast<std::size_t>(info.size * info.itemsize)};
}

// decode(view) (an lcm-gen class's decode); what it raises becomes BadRequest (GIL held).
py::object decode_or_bad_request(const py::object& decode, py::object& view, const std::string& type_name);

// ---- the handles every part hangs from ----

struct PyRuntime final : Closable {
  std::optional<lcmx::Runtime> rt;
  std::shared_ptr<CallbackBox> events = std::make_shared<CallbackBox>();
  // Nodes and endpoints made from it, creation order (GIL): the runtime keeps them alive until
  // they or it are closed, as rclpy's nodes keep their subscriptions (no handle to hold).
  std::vector<std::shared_ptr<Closable>> children;
  bool closed() const override { return !rt; }
  lcmx::Runtime& get() {
    if (!rt) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx.Runtime is closed");
    return *rt;
  }
  void adopt(const std::shared_ptr<Closable>& c) {
    std::erase_if(children, [](const auto& c) { return c->closed(); });
    children.push_back(c);
    register_closable(c);
  }
  // Closes every node and endpoint made from it (newest first), then the runtime: nothing of
  // it (shared memory, threads) outlives close(), whatever Python still references.
  void close() override {
    std::vector<std::shared_ptr<Closable>> kids;
    kids.swap(children);
    for (auto it = kids.rbegin(); it != kids.rend(); ++it) (*it)->close();
    events->clear();
    std::optional<lcmx::Runtime> old;
    old.swap(rt);
    py::gil_scoped_release nogil;
    old.reset();
  }
  ~PyRuntime() override {
    if (rt && !g_exiting.load()) {
      py::gil_scoped_release nogil;
      rt.reset();
    }
  }
};


inline std::weak_ptr<PyRuntime> g_runtime;  // the process's runtime (there is at most one)

struct PyNode final : Closable {
  std::shared_ptr<PyRuntime> runtime;  // keeps the Python runtime (and its events box) alive
  std::shared_ptr<lcmx::Node> node;
  bool closed() const override { return !node; }
  std::shared_ptr<lcmx::Node> get() {
    if (!node) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx.Node is closed");
    return node;
  }
  void close() override {
    auto old = std::move(node);
    drop(old);
  }
  ~PyNode() override {
    if (node && !g_exiting.load()) {
      py::gil_scoped_release nogil;
      node.reset();
    }
  }
};

using NodeClass = py::class_<PyNode, std::shared_ptr<PyNode>>;

// Each part binds its classes into `m` and its factories onto _Node (runtime.cpp binds _Node).
NodeClass bind_runtime(py::module_& m);
void bind_pubsub(py::module_& m, NodeClass& node);
void bind_services(py::module_& m, NodeClass& node);
void bind_actions(py::module_& m, NodeClass& node);
void bind_lcm(py::module_& m);

}  // namespace lcmxpy
