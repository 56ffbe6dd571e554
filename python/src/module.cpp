// lcmx._lcmx: the pybind11 layer under the `lcmx` Python package (python/lcmx/__init__.py).
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
#include <pybind11/functional.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <sys/eventfd.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstring>
#include <deque>
#include <future>
#include <list>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <regex>
#include <shared_mutex>
#include <string>
#include <vector>

#include <spdlog/spdlog.h>

#include "lcmx/core.hpp"  // the runtime and lcmx::services (services, actions)

namespace py = pybind11;
using namespace std::chrono_literals;

namespace {

std::atomic<bool> g_exiting{false};

// Anything a Python handle owns in C++ that must be dropped before the interpreter ends.
struct Closable {
  virtual ~Closable() = default;
  // Called with the GIL held; releases it while waiting for lcmx threads.
  virtual void close() = 0;
  virtual bool closed() const = 0;
};

std::mutex g_registry_mu;
std::list<std::weak_ptr<Closable>> g_registry;  // creation order

void register_closable(const std::shared_ptr<Closable>& c) {
  std::lock_guard lock(g_registry_mu);
  for (auto it = g_registry.begin(); it != g_registry.end();)
    it = it->expired() ? g_registry.erase(it) : std::next(it);
  g_registry.push_back(c);
}

// atexit: newest first (subscribers before nodes before runtimes).
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

void report_callback_error(CallbackBox& box, const std::string& where, py::error_already_set& e) {
  const auto n = box.errors.fetch_add(1) + 1;
  spdlog::error("lcmx: python callback on '{}' raised ({} so far): {}", where, n, e.what());
}

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

py::dict to_dict(const lcmx::SubscriberStats& s, std::uint64_t callback_errors) {
  py::dict d;
  d["delivered"] = s.delivered;
  d["drops"] = s.drops;
  d["decode_errors"] = s.decode_errors;
  d["callback_errors"] = callback_errors;
  d["errors"] = s.errors;
  py::list pubs;
  for (const auto& p : s.publishers) {
    py::dict e;
    e["participant"] = p.publisher_participant;
    e["endpoint"] = p.publisher_endpoint;
    e["path"] = lcmx::to_string(p.path);
    e["received"] = p.received;
    e["drops"] = p.drops;
    pubs.append(e);
  }
  d["publishers"] = pubs;
  return d;
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

std::chrono::milliseconds slice_ms(std::chrono::nanoseconds slice) {
  return std::max(std::chrono::duration_cast<std::chrono::milliseconds>(slice), std::chrono::milliseconds(1));
}

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

std::weak_ptr<PyRuntime> g_runtime;  // the process's runtime (there is at most one)

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

struct PyPublisher final : Closable {
  std::shared_ptr<PyNode> node;
  std::shared_ptr<lcmx::RawPublisher> pub;
  bool closed() const override { return !pub; }
  std::shared_ptr<lcmx::RawPublisher> get() {
    if (!pub) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx publisher is closed");
    return pub;
  }
  void publish(const py::buffer& data) {
    lcmx::RawPublisher p = *get();  // a handle of our own (shares the publisher)
    py::buffer_info info = data.request();  // holds the buffer while the GIL is released
    if (!PyBuffer_IsContiguous(info.view(), 'C'))
      throw lcmx::Error(lcmx::Errc::invalid_argument, "publish: the buffer is not contiguous");
    std::span<const std::byte> bytes(static_cast<const std::byte*>(info.ptr),
                                     static_cast<std::size_t>(info.size * info.itemsize));
    py::gil_scoped_release nogil;
    p.publish(bytes);
  }
  void close() override {
    auto old = std::move(pub);
    drop(old);
  }
  ~PyPublisher() override {
    if (pub && !g_exiting.load()) {
      py::gil_scoped_release nogil;
      pub.reset();
    }
  }
};

// A slot loaned from a raw publisher (zero-copy publish): `view` is a writable memoryview of
// it until publish() or drop(), which release the view first and refuse (lcmx.Error) while
// something still exports it (e.g. a numpy array over it), since the slot is then reused.
struct PyLoan {
  lcmx::RawPublisher pub;  // a handle of our own (shares the publisher)
  lcmx::Loan loan;
  std::size_t size = 0;
  std::optional<SlotView> slot;  // GIL

  void release_view() {
    if (slot && !slot->try_release())
      throw lcmx::Error(lcmx::Errc::invalid_argument,
                        "the loan's memory is still referred to (a slice, cast or array of its view): "
                        "delete those first");
    if (slot) slot->revoke();
    slot.reset();
  }
  bool open() const { return loan.data() != nullptr; }
  void publish(std::optional<std::size_t> n) {
    if (!open()) throw lcmx::Error(lcmx::Errc::invalid_argument, "the loan was already published or dropped");
    const std::size_t bytes = n.value_or(size);
    if (bytes > size)
      throw lcmx::Error(lcmx::Errc::invalid_argument,
                        "publish: " + std::to_string(bytes) + " bytes from a loan of " + std::to_string(size));
    release_view();
    py::gil_scoped_release nogil;
    pub.publish(std::move(loan), bytes);
  }
  void drop() {
    if (!open()) return;
    release_view();
    py::gil_scoped_release nogil;
    loan = lcmx::Loan();
  }
  ~PyLoan() {
    // The loan's last Python reference is going (GIL held): revoke the memory, drop the slot.
    if (slot) slot->revoke();
    slot.reset();
    if (open() && !g_exiting.load()) {
      py::gil_scoped_release nogil;
      loan = lcmx::Loan();
    }
  }
};

struct PySubscriber final : Closable {
  std::shared_ptr<PyNode> node;
  std::shared_ptr<lcmx::RawSubscriber> sub;
  std::shared_ptr<CallbackBox> box;
  bool closed() const override { return !sub; }
  std::shared_ptr<lcmx::RawSubscriber> get() {
    if (!sub) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx subscriber is closed");
    return sub;
  }
  void close() override {
    if (box) box->clear();  // a callback waiting for the GIL then returns at once
    auto old = std::move(sub);
    drop(old);  // waits for a running callback (unless called from inside it)
  }
  ~PySubscriber() override {
    if (sub && !g_exiting.load()) {
      if (box) box->clear();
      py::gil_scoped_release nogil;
      sub.reset();
    }
  }
};

// ---- services over raw bytes (typed in python/lcmx/__init__.py) ----

struct PyService final : Closable {
  std::shared_ptr<lcmx::Service> svc;
  std::shared_ptr<CallbackBox> box;
  bool closed() const override { return !svc; }
  void close() override {
    if (box) box->clear();
    auto old = std::move(svc);
    drop(old);
  }
  ~PyService() override {
    if (svc && !g_exiting.load()) {
      if (box) box->clear();
      drop(svc);
    }
  }
};

struct PyClient final : Closable {
  std::shared_ptr<lcmx::RawClient> cli;
  bool closed() const override { return !cli; }
  std::shared_ptr<lcmx::RawClient> get() {
    if (!cli) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx client is closed");
    return cli;
  }
  void close() override {
    auto old = std::move(cli);
    drop(old);
  }
  ~PyClient() override {
    if (cli && !g_exiting.load()) drop(cli);
  }
};

// ---- typed endpoints: lcm-gen type names and fingerprints from python/lcmx/__init__.py ----

std::chrono::milliseconds to_ms(double seconds) {
  if (!(seconds >= 0.0)) throw lcmx::Error(lcmx::Errc::invalid_argument, "a timeout must be >= 0 seconds");
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::duration<double>(seconds));
}

// None: raw bytes; else (request_name, response_name, request_fingerprint, response_fingerprint).
lcmx::detail::ServiceTypes service_types(const py::object& t) {
  if (t.is_none()) return {};
  auto v = t.cast<std::tuple<std::string, std::string, std::int64_t, std::int64_t>>();
  return {std::get<0>(v), std::get<1>(v), std::get<2>(v), std::get<3>(v)};
}

// None: raw bytes; else (goal, feedback, result names, then their fingerprints).
lcmx::detail::ActionTypes action_types(const py::object& t) {
  if (t.is_none()) return {};
  auto v = t.cast<std::tuple<std::string, std::string, std::string, std::int64_t, std::int64_t, std::int64_t>>();
  return {std::get<0>(v), std::get<1>(v), std::get<2>(v), std::get<3>(v), std::get<4>(v), std::get<5>(v)};
}

// decode(view) (an lcm-gen class's decode); what it raises becomes BadRequest (GIL held).
py::object decode_or_bad_request(const py::object& decode, py::object& view, const std::string& type_name) {
  try {
    return decode(view);
  } catch (py::error_already_set& e) {
    throw lcmx::detail::BadRequest("the payload did not decode as " + type_name + ": " + e.what());
  }
}

py::tuple to_tuple(const lcmx::GoalStatus& s) {
  return py::make_tuple(s.goal_id, lcmx::to_string(s.state), s.message);
}

py::bytes to_bytes(std::span<const std::byte> b) {
  return py::bytes(reinterpret_cast<const char*>(b.data()), b.size());
}

std::span<const std::byte> buffer_bytes(const py::buffer_info& info) {
  return {static_cast<const std::byte*>(info.ptr), static_cast<std::size_t>(info.size * info.itemsize)};
}

// ---- actions over raw bytes (typed in python/lcmx/__init__.py) ----

// The server's goal as Python holds it: valid while its execute runs. Calls from Python take
// `mu` shared without the GIL; execute's end takes it exclusively, so a call made from
// another Python thread never uses the goal after execute returned (it raises instead).
struct PyGoalHandle {
  explicit PyGoalHandle(lcmx::RawActionGoal* r) : raw(r), id(r->id()) {}
  lcmx::RawActionGoal* raw;  // null once execute returned
  std::string id;
  std::shared_mutex mu;

  template <class F>
  auto with(F&& f) {  // GIL held on entry; released during f
    py::gil_scoped_release nogil;
    std::shared_lock lock(mu);
    if (!raw)
      throw lcmx::Error(lcmx::Errc::invalid_argument,
                        "action goal " + id + ": its execute has returned; the handle is no longer valid");
    return f(*raw);
  }
  void invalidate() {  // GIL held on entry
    py::gil_scoped_release nogil;
    std::unique_lock lock(mu);
    raw = nullptr;
  }
};

lcmx::GoalState end_state(const std::string& s) {
  if (s == "succeeded") return lcmx::GoalState::succeeded;
  if (s == "aborted") return lcmx::GoalState::aborted;
  if (s == "canceled") return lcmx::GoalState::canceled;
  throw lcmx::Error(lcmx::Errc::invalid_argument, "a goal ends succeeded, aborted or canceled, not '" + s + "'");
}

struct PyActionServer final : Closable {
  std::shared_ptr<lcmx::ActionServer> srv;
  std::shared_ptr<CallbackBox> execute, accept;
  bool closed() const override { return !srv; }
  std::shared_ptr<lcmx::ActionServer> get() {
    if (!srv) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx action server is closed");
    return srv;
  }
  // Cancels live goals and waits for their execute (without the GIL, which they need).
  void close() override {
    execute->clear();  // goals accepted but not started end at once (aborted)
    accept->clear();   // new goals are rejected
    auto old = std::move(srv);
    drop(old);
  }
  ~PyActionServer() override {
    if (srv && !g_exiting.load()) {
      execute->clear();
      accept->clear();
      drop(srv);
    }
  }
};

// `execute(handle, goal)` runs on a thread of its own per goal (GIL taken for the call); goal is
// decode(view) or bytes. `accept(goal)` (None: every goal) runs on the node's executor and
// returns bool or str ("" accepts, other text rejects with it). What execute raises aborts the
// goal with its text; what accept raises rejects it.
std::shared_ptr<PyActionServer> create_action_server(const std::shared_ptr<PyNode>& n, std::string name,
                                                     py::object execute, py::object accept, py::object types,
                                                     py::object decode, std::size_t max_goals,
                                                     double status_period, double client_timeout,
                                                     double result_retention) {
  if (!PyCallable_Check(execute.ptr()))
    throw lcmx::Error(lcmx::Errc::invalid_argument, "create_action_server: execute is not callable");
  if (!accept.is_none() && !PyCallable_Check(accept.ptr()))
    throw lcmx::Error(lcmx::Errc::invalid_argument, "create_action_server: accept is not callable (or None)");
  auto t = action_types(types);
  lcmx::ActionServerOptions o;
  o.max_goals = max_goals;
  o.status_period = to_ms(status_period);
  o.client_timeout = to_ms(client_timeout);
  o.result_retention = to_ms(result_retention);
  auto s = std::make_shared<PyActionServer>();
  s->execute = std::make_shared<CallbackBox>();
  s->execute->fn = std::move(execute);
  s->execute->decode = decode;
  s->accept = std::make_shared<CallbackBox>();
  s->accept->fn = std::move(accept);  // None stays an object: cleared (null) means closed
  s->accept->decode = std::move(decode);
  const std::string where = name, goal_name = t.goal_name;

  auto acc = [box = s->accept, where, goal_name](std::span<const std::byte> in) -> std::string {
    if (g_exiting.load()) return "the Python interpreter is exiting";
    ExecutorGil gil;
    if (!box->fn) return "the action server is closed";
    std::string verdict;
    with_view(in, [&](py::object& view) {
      py::object goal = view;
      if (box->decode && !box->decode.is_none()) goal = decode_or_bad_request(box->decode, view, goal_name);
      if (box->fn.is_none()) return;
      try {
        py::object r = box->fn(goal);
        if (py::isinstance<py::bool_>(r)) verdict = r.cast<bool>() ? "" : "rejected by the server";
        else if (py::isinstance<py::str>(r)) verdict = r.cast<std::string>();
        else throw py::type_error("accept returned " + std::string(py::str(r.get_type().attr("__name__"))) +
                                  ", not bool or str");
      } catch (py::error_already_set& e) {
        report_callback_error(*box, where + " (accept)", e);
        verdict = std::string("accept raised: ") + e.what();
      } catch (py::type_error& e) {
        spdlog::error("lcmx: python accept of action '{}': {}", where, e.what());
        verdict = e.what();
      }
    });
    return verdict;
  };

  auto exe = [box = s->execute, where](lcmx::RawActionGoal& raw) {
    if (g_exiting.load()) return;  // ends aborted ("returned without ending the goal")
    py::gil_scoped_acquire gil;
    if (!box->fn) return;
    py::object fn = box->fn;  // our own reference: close() may clear the box meanwhile
    auto handle = std::make_shared<PyGoalHandle>(&raw);
    std::string failure;
    try {
      py::object goal;
      if (box->decode && !box->decode.is_none())
        with_view(raw.goal(), [&](py::object& view) { goal = box->decode(view); });
      else
        goal = to_bytes(raw.goal());
      fn(handle, goal);
    } catch (py::error_already_set& e) {
      report_callback_error(*box, where + " (execute)", e);
      failure = e.what();
    }
    handle->invalidate();
    if (!failure.empty()) throw std::runtime_error(failure);  // the goal ends aborted with it
  };

  s->srv = std::make_shared<lcmx::ActionServer>(
      n->get()->create_action_server_raw(std::move(name), std::move(t), std::move(exe), std::move(acc), o));
  n->runtime->adopt(s);
  return s;
}

// A goal sent by a Python action client (or named by id).
struct PyClientGoal {
  lcmx::ClientGoal<lcmx::Bytes> goal;
};

struct PyActionClient final : Closable {
  std::shared_ptr<lcmx::RawActionClient> cli;
  std::vector<std::shared_ptr<CallbackBox>> feedback;  // GIL: one per goal sent with a callback
  bool closed() const override { return !cli; }
  std::shared_ptr<lcmx::RawActionClient> get() {
    if (!cli) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx action client is closed");
    return cli;
  }
  void close() override {
    for (auto& b : feedback) b->clear();
    feedback.clear();
    auto old = std::move(cli);
    drop(old);
  }
  ~PyActionClient() override {
    if (cli && !g_exiting.load()) {
      for (auto& b : feedback) b->clear();
      drop(cli);
    }
  }
};

// Waits for a goal's end in slices (Ctrl-C raises KeyboardInterrupt). Returns (True, state,
// message, result bytes or None) or (False, error code, message).
py::tuple wait_goal(const lcmx::ClientGoal<lcmx::Bytes>& goal, std::optional<double> timeout_s) {
  std::optional<lcmx::CallResult<lcmx::GoalOutcome<lcmx::Bytes>>> result;
  wait_interruptible(timeout_s, [&](std::chrono::nanoseconds slice) {
    // Once the goal ended, fetching its result gets a full second (not a slice's end).
    const bool ended = lcmx::is_terminal(goal.status().state);
    auto ms = std::max(std::chrono::duration_cast<std::chrono::milliseconds>(slice), 1ms);
    if (ended) ms = std::max(ms, std::chrono::milliseconds(1000));
    auto r = goal.wait(ms);
    if (!r.ok() && r.error() == lcmx::CallErrc::timeout && !ended) {
      result = std::move(r);  // still live: the last answer, if the deadline passes
      return false;
    }
    result = std::move(r);
    return true;
  });
  if (!result) return py::make_tuple(false, "timeout", "the goal did not end within the timeout");
  if (!result->ok()) return py::make_tuple(false, lcmx::to_string(result->error()), result->message());
  const auto& o = result->value();
  py::object res = py::none();
  if (o.result) res = to_bytes(*o.result);
  return py::make_tuple(true, to_tuple(o.status), res);
}

void bind_actions(py::module_& m) {
  py::class_<PyGoalHandle, std::shared_ptr<PyGoalHandle>>(m, "_ActionGoal")
      .def_property_readonly("id", [](PyGoalHandle& h) { return h.id; })
      .def("cancel_requested", [](PyGoalHandle& h) { return h.with([](lcmx::RawActionGoal& g) { return g.cancel_requested(); }); })
      .def("wait_for_cancel",
           [](PyGoalHandle& h, std::optional<double> timeout) {
             // In slices: another thread's end of the goal (or Ctrl-C on the main thread) is seen.
             return wait_interruptible(timeout, [&](std::chrono::nanoseconds slice) {
               std::shared_lock lock(h.mu);
               if (!h.raw)
                 throw lcmx::Error(lcmx::Errc::invalid_argument,
                                   "action goal " + h.id + ": its execute has returned; the handle is no longer valid");
               return h.raw->wait_for_cancel(slice);
             });
           },
           py::arg("timeout") = py::none())
      .def("publish_feedback",
           [](PyGoalHandle& h, const py::buffer& data) {
             py::buffer_info info = data.request();
             auto bytes = buffer_bytes(info);
             h.with([&](lcmx::RawActionGoal& g) { g.publish_feedback(bytes); });
           },
           py::arg("data"))
      .def("finish",
           [](PyGoalHandle& h, const std::string& state, const py::buffer& result, const std::string& message) {
             const auto s = end_state(state);
             py::buffer_info info = result.request();
             auto bytes = buffer_bytes(info);
             h.with([&](lcmx::RawActionGoal& g) { g.finish(s, bytes, message); });
           },
           py::arg("state"), py::arg("result"), py::arg("message") = "")
      .def("finished", [](PyGoalHandle& h) { return h.with([](lcmx::RawActionGoal& g) { return g.finished(); }); });

  py::class_<PyActionServer, std::shared_ptr<PyActionServer>>(m, "_ActionServer")
      .def("close", &PyActionServer::close)
      .def_property_readonly("name", [](PyActionServer& s) { return s.get()->name(); })
      .def_property_readonly("execute_errors", [](PyActionServer& s) { return s.execute->errors.load(); })
      .def("stats",
           [](PyActionServer& s) {
             auto srv = s.get();
             lcmx::ActionServerStats st;
             {
               py::gil_scoped_release nogil;
               st = srv->stats();
             }
             py::dict d;
             d["accepted"] = st.accepted;
             d["rejected"] = st.rejected;
             d["succeeded"] = st.succeeded;
             d["aborted"] = st.aborted;
             d["canceled"] = st.canceled;
             d["cancel_requests"] = st.cancel_requests;
             d["client_gone_cancels"] = st.client_gone_cancels;
             d["executing"] = st.executing;
             return d;
           })
      .def("goals", [](PyActionServer& s) {
        auto srv = s.get();
        std::vector<lcmx::GoalStatus> goals;
        {
          py::gil_scoped_release nogil;
          goals = srv->goals();
        }
        py::list l;
        for (const auto& g : goals) l.append(to_tuple(g));
        return l;
      });

  py::class_<PyClientGoal, std::shared_ptr<PyClientGoal>>(m, "_ClientGoal")
      .def_property_readonly("id", [](PyClientGoal& g) { return g.goal.id(); })
      .def_property_readonly("accepted", [](PyClientGoal& g) { return g.goal.accepted(); })
      .def_property_readonly("message", [](PyClientGoal& g) { return g.goal.message(); })
      .def("status",
           [](PyClientGoal& g) {
             lcmx::GoalStatus s;
             {
               py::gil_scoped_release nogil;
               s = g.goal.status();
             }
             return to_tuple(s);
           })
      .def("wait", [](PyClientGoal& g, std::optional<double> timeout) { return wait_goal(g.goal, timeout); },
           py::arg("timeout") = py::none())
      .def("cancel",
           [](PyClientGoal& g, double timeout) {
             const auto ms = to_ms(timeout);
             std::optional<lcmx::CallResult<lcmx::GoalStatus>> r;
             {
               py::gil_scoped_release nogil;
               r = g.goal.cancel(ms);
             }
             if (!r->ok()) return py::make_tuple(false, lcmx::to_string(r->error()), r->message());
             return py::make_tuple(true, to_tuple(r->value()), "");
           },
           py::arg("timeout") = 1.0);

  py::class_<PyActionClient, std::shared_ptr<PyActionClient>>(m, "_ActionClient")
      .def("close", &PyActionClient::close)
      .def_property_readonly("name", [](PyActionClient& c) { return c.get()->name(); })
      .def("wait_for_server",
           [](PyActionClient& c, double timeout) {
             return wait_on(c.get(), timeout, [](lcmx::RawActionClient& cli, std::chrono::nanoseconds slice) {
               return cli.wait_for_server(slice_ms(slice));
             });
           },
           py::arg("timeout") = 10.0)
      // Returns (True, goal) — rejected goals too (goal.accepted) — or (False, code, message).
      .def("send_goal",
           [](PyActionClient& c, const py::buffer& goal, double timeout, py::object on_feedback,
              py::object decode) -> py::tuple {
             if (!on_feedback.is_none() && !PyCallable_Check(on_feedback.ptr()))
               throw lcmx::Error(lcmx::Errc::invalid_argument, "send_goal: on_feedback is not callable (or None)");
             auto cli = c.get();
             const auto ms = to_ms(timeout);
             std::function<void(std::span<const std::byte>)> fb;
             if (!on_feedback.is_none()) {
               auto box = std::make_shared<CallbackBox>();
               box->fn = std::move(on_feedback);
               box->decode = std::move(decode);
               std::erase_if(c.feedback, [](const auto& b) { return !b->fn; });
               c.feedback.push_back(box);
               std::string where = cli->name() + " (feedback)";
               fb = [box, where](std::span<const std::byte> b) {  // the client's thread
                 if (g_exiting.load()) return;
                 ExecutorGil gil;
                 if (!box->fn) return;
                 try {
                   with_view(b, [&](py::object& view) {
                     if (box->decode && !box->decode.is_none()) box->fn(box->decode(view));
                     else box->fn(view);
                   });
                 } catch (py::error_already_set& e) {
                   report_callback_error(*box, where, e);
                 }
               };
             }
             py::buffer_info info = goal.request();
             auto bytes = buffer_bytes(info);
             std::optional<lcmx::CallResult<lcmx::ClientGoal<lcmx::Bytes>>> r;
             {
               py::gil_scoped_release nogil;
               r = cli->send_goal(bytes, ms, std::move(fb));
               cli.reset();
             }
             if (!r->ok()) return py::make_tuple(false, lcmx::to_string(r->error()), r->message());
             return py::make_tuple(true, std::make_shared<PyClientGoal>(PyClientGoal{r->value()}));
           },
           py::arg("goal"), py::arg("timeout") = 10.0, py::arg("on_feedback") = py::none(),
           py::arg("decode") = py::none())
      .def("goal", [](PyActionClient& c, const std::string& id) {
        return std::make_shared<PyClientGoal>(PyClientGoal{c.get()->goal(id)});
      })
      .def("status",
           [](PyActionClient& c, const std::string& id) {
             auto cli = c.get();
             lcmx::GoalStatus s;
             {
               py::gil_scoped_release nogil;
               s = cli->status(id);
               cli.reset();
             }
             return to_tuple(s);
           })
      .def("goals", [](PyActionClient& c) {
        auto cli = c.get();
        std::vector<lcmx::GoalStatus> goals;
        {
          py::gil_scoped_release nogil;
          goals = cli->goals();
          cli.reset();
        }
        py::list l;
        for (const auto& g : goals) l.append(to_tuple(g));
        return l;
      });
}

// ---- the LCM drop-in's C++ half: messages queued by lcmx threads, handled by the caller ----

struct PyLcm final : Closable {
  struct Sub {
    std::uint64_t id = 0;
    lcmx::ChannelSubscription subscription;
    py::object handler;  // GIL
    std::size_t capacity = 30;
    std::atomic<std::size_t> queued{0};
    std::atomic<std::uint64_t> dropped{0};
  };
  struct Item {
    std::shared_ptr<Sub> sub;
    std::string channel;
    std::vector<std::byte> data;
  };

  std::shared_ptr<PyRuntime> runtime;
  std::optional<lcmx::Node> node;
  std::map<std::string, lcmx::RawPublisher> pubs;  // GIL
  std::map<std::uint64_t, std::shared_ptr<Sub>> subs;  // GIL
  std::uint64_t next_id = 1;
  int efd = -1;  // readable while the queue is not empty
  std::mutex mu;
  std::condition_variable cv;
  std::deque<Item> queue;

  PyLcm() {
    efd = ::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (efd < 0) throw lcmx::Error(lcmx::Errc::transport, "lcmx.LCM: eventfd failed");
  }
  ~PyLcm() override {
    if (!g_exiting.load()) {
      for (auto& [id, s] : subs) s->handler = py::object();
      py::gil_scoped_release nogil;
      drop_cpp();
    } else {
      for (auto& [id, s] : subs) s->handler.release();
    }
    if (efd >= 0) ::close(efd);
  }
  void drop_cpp() {
    for (auto& [id, s] : subs) s->subscription.reset();
    pubs.clear();
    node.reset();
  }
  void close() override {
    std::map<std::uint64_t, std::shared_ptr<Sub>> old;
    old.swap(subs);
    for (auto& [id, s] : old) s->handler = py::object();
    py::gil_scoped_release nogil;
    for (auto& [id, s] : old) s->subscription.reset();
    pubs.clear();
    node.reset();
  }
  bool closed() const override { return !node; }
  lcmx::Node& get() {
    if (!node) throw lcmx::Error(lcmx::Errc::invalid_argument, "the lcmx.LCM is closed");
    return *node;
  }

  void publish(const std::string& channel, const py::buffer& data) {
    auto& n = get();
    auto it = pubs.find(channel);
    if (it == pubs.end()) it = pubs.emplace(channel, n.advertise_raw(channel)).first;
    py::buffer_info info = data.request();
    std::span<const std::byte> bytes(static_cast<const std::byte*>(info.ptr),
                                     static_cast<std::size_t>(info.size * info.itemsize));
    lcmx::RawPublisher pub = it->second;  // our own handle: close() may clear pubs meanwhile
    py::gil_scoped_release nogil;
    pub.publish(bytes);
  }

  std::shared_ptr<Sub> subscribe(const std::string& pattern, py::object handler) {
    auto& n = get();
    auto re = std::make_shared<std::regex>(pattern, std::regex::ECMAScript);  // throws on a bad regex
    auto s = std::make_shared<Sub>();
    s->id = next_id++;
    s->handler = std::move(handler);
    std::weak_ptr<Sub> weak = s;
    s->subscription = n.subscribe_channels(
        [re](const std::string& channel) { return std::regex_match(channel, *re); },
        [this, weak](const lcmx::RawMessage& m) {  // executor thread, no GIL
          auto sub = weak.lock();
          if (!sub) return;
          if (sub->queued.load() >= sub->capacity && sub->capacity > 0) {
            sub->dropped.fetch_add(1);
            return;
          }
          Item item{sub, std::string(m.channel), std::vector<std::byte>(m.data.begin(), m.data.end())};
          std::lock_guard lock(mu);
          sub->queued.fetch_add(1);
          if (queue.empty()) {
            const std::uint64_t one = 1;
            [[maybe_unused]] auto w = ::write(efd, &one, sizeof one);
          }
          queue.push_back(std::move(item));
          cv.notify_one();
        });
    subs.emplace(s->id, s);
    return s;
  }

  void unsubscribe(const std::shared_ptr<Sub>& s) {
    if (!s || subs.erase(s->id) == 0)
      throw lcmx::Error(lcmx::Errc::invalid_argument, "unsubscribe: not a subscription of this LCM");
    s->handler = py::object();
    py::gil_scoped_release nogil;
    s->subscription.reset();
  }

  // Pops one message (waiting up to `timeout`); GIL not held.
  std::optional<Item> pop(std::chrono::nanoseconds timeout) {
    std::unique_lock lock(mu);
    if (!cv.wait_for(lock, timeout, [&] { return !queue.empty(); })) return std::nullopt;
    Item item = std::move(queue.front());
    queue.pop_front();
    item.sub->queued.fetch_sub(1);
    if (queue.empty()) {
      std::uint64_t v;
      [[maybe_unused]] auto r = ::read(efd, &v, sizeof v);
    }
    return item;
  }

  // Handles one message; returns false if none came within `timeout` (None: forever).
  bool handle(std::optional<double> timeout_s) {
    get();
    std::optional<Item> item;
    const bool got = wait_interruptible(timeout_s, [&](std::chrono::nanoseconds slice) {
      item = pop(slice);
      return item.has_value();
    });
    if (!got) return false;
    if (!item->sub->handler) return true;  // unsubscribed since: consumed, like LCM
    py::bytes data(reinterpret_cast<const char*>(item->data.data()), item->data.size());
    item->sub->handler(item->channel, data);  // exceptions propagate, as in LCM's handle()
    return true;
  }
};

}  // namespace

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

  py::class_<PyNode, std::shared_ptr<PyNode>>(m, "_Node")
      .def("close", &PyNode::close)
      .def_property_readonly("name", [](PyNode& n) { return n.get()->name(); })
      .def("advertise_raw",
           [](const std::shared_ptr<PyNode>& n, std::string channel, std::optional<std::string> type_name,
              std::int64_t fingerprint, std::size_t max_message_size, std::uint32_t shm_slots,
              std::uint32_t history) {
             lcmx::PublisherOptions o;
             o.max_message_size = max_message_size;
             o.shm_slots = shm_slots;
             o.history = history;
             auto p = std::make_shared<PyPublisher>();
             p->node = n;
             auto node = n->get();
             p->pub = std::make_shared<lcmx::RawPublisher>(
                 type_name ? node->advertise_raw(std::move(channel), *type_name, fingerprint, o)
                           : node->advertise_raw(std::move(channel), o));
             n->runtime->adopt(p);
             return p;
           },
           py::arg("channel"), py::arg("type_name") = py::none(), py::arg("fingerprint") = 0,
           py::arg("max_message_size") = std::size_t{64} << 20, py::arg("shm_slots") = 8,
           py::arg("history") = 0)
      .def("subscribe_raw",
           [](const std::shared_ptr<PyNode>& n, std::string channel, py::object callback,
              std::optional<std::string> type_name, std::int64_t fingerprint, py::object decode,
              std::size_t queue_depth) {
             if (!PyCallable_Check(callback.ptr()))
               throw lcmx::Error(lcmx::Errc::invalid_argument, "subscribe: the callback is not callable");
             auto box = std::make_shared<CallbackBox>();
             box->fn = std::move(callback);
             box->decode = std::move(decode);
             std::string where = channel;
             auto cb = [box, where](const lcmx::RawMessage& msg) {  // executor thread
               if (g_exiting.load()) return;
               ExecutorGil gil;
               if (!box->fn) return;  // closed
               try {
                 with_view(msg.data, [&](py::object& view) {
                   if (box->decode && !box->decode.is_none()) {
                     py::object obj = box->decode(view);
                     box->fn(obj);
                   } else {
                     box->fn(view);
                   }
                 });
               } catch (py::error_already_set& e) {
                 report_callback_error(*box, where, e);
               }
             };
             lcmx::SubscriberOptions o;
             o.queue_depth = queue_depth;
             auto s = std::make_shared<PySubscriber>();
             s->node = n;
             s->box = box;
             auto node = n->get();
             s->sub = std::make_shared<lcmx::RawSubscriber>(
                 type_name ? node->subscribe_raw(std::move(channel), *type_name, fingerprint, cb, o)
                           : node->subscribe_raw(std::move(channel), cb, o));
             n->runtime->adopt(s);
             return s;
           },
           py::arg("channel"), py::arg("callback"), py::arg("type_name") = py::none(),
           py::arg("fingerprint") = 0, py::arg("decode") = py::none(), py::arg("queue_depth") = 16)
      .def("create_service_raw",
           [](const std::shared_ptr<PyNode>& n, std::string name, py::object handler, py::object types,
              py::object decode) {
             if (!PyCallable_Check(handler.ptr()))
               throw lcmx::Error(lcmx::Errc::invalid_argument, "create_service: the handler is not callable");
             auto t = service_types(types);
             auto box = std::make_shared<CallbackBox>();
             box->fn = std::move(handler);
             box->decode = std::move(decode);
             std::string where = name;
             std::string request_name = t.request_name;
             // On the node's executor. A request that `decode` refuses is bad_request; what
             // the handler raises reaches the client as handler_failed with its text.
             auto h = [box, where, request_name](std::span<const std::byte> in, lcmx::ResponseWriter& out) {
               if (g_exiting.load()) throw std::runtime_error("the Python interpreter is exiting");
               ExecutorGil gil;
               if (!box->fn) throw std::runtime_error("the service is closed");
               try {
                 py::object r;
                 with_view(in, [&](py::object& view) {
                   py::object arg = view;
                   if (box->decode && !box->decode.is_none()) arg = decode_or_bad_request(box->decode, view, request_name);
                   r = box->fn(arg);
                 });
                 if (!PyObject_CheckBuffer(r.ptr()))
                   throw std::runtime_error("the handler did not return a bytes-like object");
                 py::buffer_info info = py::reinterpret_borrow<py::buffer>(r).request();
                 const auto size = static_cast<std::size_t>(info.size * info.itemsize);
                 auto dst = out.allocate(size);
                 std::memcpy(dst.data(), info.ptr, size);
               } catch (py::error_already_set& e) {
                 report_callback_error(*box, where, e);
                 throw std::runtime_error(e.what());
               }
             };
             auto s = std::make_shared<PyService>();
             s->box = box;
             s->svc = std::make_shared<lcmx::Service>(
                 n->get()->create_service_raw(std::move(name), std::move(t), std::move(h)));
             n->runtime->adopt(s);
             return s;
           },
           py::arg("name"), py::arg("handler"), py::arg("types") = py::none(), py::arg("decode") = py::none())
      .def("create_client_raw",
           [](const std::shared_ptr<PyNode>& n, std::string name, py::object types) {
             auto c = std::make_shared<PyClient>();
             c->cli = std::make_shared<lcmx::RawClient>(n->get()->create_client_raw(std::move(name), service_types(types)));
             n->runtime->adopt(c);
             return c;
           },
           py::arg("name"), py::arg("types") = py::none())
      .def("create_action_server_raw", &create_action_server, py::arg("name"), py::arg("execute"),
           py::arg("accept") = py::none(), py::arg("types") = py::none(), py::arg("decode") = py::none(),
           py::arg("max_goals") = 16, py::arg("status_period") = 1.0, py::arg("client_timeout") = 5.0,
           py::arg("result_retention") = 60.0)
      .def("create_action_client_raw",
           [](const std::shared_ptr<PyNode>& n, std::string name, py::object types) {
             auto c = std::make_shared<PyActionClient>();
             c->cli = std::make_shared<lcmx::RawActionClient>(
                 n->get()->create_action_client_raw(std::move(name), action_types(types)));
             n->runtime->adopt(c);
             return c;
           },
           py::arg("name"), py::arg("types") = py::none())
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

  py::class_<PyService, std::shared_ptr<PyService>>(m, "_Service")
      .def("close", &PyService::close)
      .def_property_readonly("handler_errors", [](PyService& s) { return s.box->errors.load(); });

  py::class_<PyClient, std::shared_ptr<PyClient>>(m, "_Client")
      .def("close", &PyClient::close)
      .def("wait_for_service",
           [](PyClient& c, double timeout) {
             return wait_on(c.get(), timeout, [](lcmx::RawClient& cli, std::chrono::nanoseconds slice) {
               return cli.wait_for_service(slice_ms(slice));
             });
           },
           py::arg("timeout") = 10.0)
      // Returns (True, response bytes, "", "", path) or (False, None, error code, message, path).
      .def("call",
           [](PyClient& c, const py::buffer& request, double timeout) {
             auto cli = c.get();
             py::buffer_info info = request.request();
             std::span<const std::byte> bytes(static_cast<const std::byte*>(info.ptr),
                                              static_cast<std::size_t>(info.size * info.itemsize));
             std::future<lcmx::RawClient::Result> fut;
             {
               py::gil_scoped_release nogil;
               fut = cli->call_async(bytes, std::chrono::duration_cast<std::chrono::milliseconds>(
                                                std::chrono::duration<double>(std::max(0.0, timeout))));
             }
             try {
               // The call ends by itself at its timeout; slices let Ctrl-C through meanwhile.
               wait_interruptible(std::nullopt, [&](std::chrono::nanoseconds slice) {
                 return fut.wait_for(slice) == std::future_status::ready;
               });
             } catch (...) {
               drop(cli);
               throw;
             }
             drop(cli);
             auto r = fut.get();
             const char* path = lcmx::to_string(r.server().path);
             if (!r.ok()) return py::make_tuple(false, py::none(), lcmx::to_string(r.error()), r.message(), path);
             const auto& v = r.value();
             return py::make_tuple(true, py::bytes(reinterpret_cast<const char*>(v.data()), v.size()), "", "", path);
           },
           py::arg("request"), py::arg("timeout") = 1.0);

  bind_actions(m);

  py::class_<PyPublisher, std::shared_ptr<PyPublisher>>(m, "_Publisher")
      .def("close", &PyPublisher::close)
      .def("publish", &PyPublisher::publish, py::arg("data"))
      .def("loan",
           [](PyPublisher& p, std::size_t size) {
             auto l = std::make_shared<PyLoan>();
             l->pub = *p.get();
             l->size = size;
             {
               py::gil_scoped_release nogil;
               l->loan = l->pub.loan(size);
             }
             l->slot.emplace(l->loan.data(), size, false);
             return l;
           },
           py::arg("size"))
      .def_property_readonly("channel", [](PyPublisher& p) { return p.get()->channel(); })
      .def("subscriber_count", [](PyPublisher& p) { return p.get()->subscriber_count(); })
      .def("wait_for_subscribers",
           [](PyPublisher& p, std::size_t n, double timeout) {
             lcmx::RawPublisher pub = *p.get();  // publisher handles copy (shared)
             return wait_interruptible(timeout, [&](std::chrono::nanoseconds slice) {
               return pub.wait_for_subscribers(n, std::chrono::duration_cast<std::chrono::milliseconds>(slice));
             });
           },
           py::arg("n") = 1, py::arg("timeout") = 10.0)
      .def("stats", [](PyPublisher& p) {
        const auto s = p.get()->stats();
        py::dict d;
        d["published"] = s.published;
        d["shm_dropped"] = s.shm_dropped;
        return d;
      });

  py::class_<PyLoan, std::shared_ptr<PyLoan>>(m, "Loan")
      .def_property_readonly("view", [](PyLoan& l) -> py::object {
        if (!l.open() || !l.slot) throw lcmx::Error(lcmx::Errc::invalid_argument, "the loan was already published or dropped");
        return l.slot->view;
      })
      .def_property_readonly("size", [](PyLoan& l) { return l.size; })
      .def("publish", &PyLoan::publish, py::arg("size") = py::none())
      .def("drop", &PyLoan::drop)
      // The context manager (lcmx.Loan): yields the view, publishes on a normal exit, drops on
      // an exception. In C++: it is on the path of every loaned message.
      .def("__enter__", [](PyLoan& l) -> py::object {
        if (!l.open() || !l.slot) throw lcmx::Error(lcmx::Errc::invalid_argument, "the loan was already published or dropped");
        return l.slot->view;
      })
      .def("__exit__", [](PyLoan& l, py::handle type, py::handle, py::handle) {
        if (type.is_none()) l.publish(std::nullopt);
        else l.drop();
        return false;
      });

  py::class_<PySubscriber, std::shared_ptr<PySubscriber>>(m, "_Subscriber")
      .def("close", &PySubscriber::close)
      .def_property_readonly("channel", [](PySubscriber& s) { return s.get()->channel(); })
      .def("publisher_count", [](PySubscriber& s) { return s.get()->publisher_count(); })
      .def("wait_for_publishers",
           [](PySubscriber& s, std::size_t n, double timeout) {
             return wait_on(s.get(), timeout, [n](lcmx::RawSubscriber& sub, std::chrono::nanoseconds slice) {
               return sub.wait_for_publishers(n, slice_ms(slice));
             });
           },
           py::arg("n") = 1, py::arg("timeout") = 10.0)
      .def("stats", [](PySubscriber& s) {
        lcmx::SubscriberStats st;
        {
          auto sub = s.get();
          py::gil_scoped_release nogil;
          st = sub->stats();
          sub.reset();
        }
        return to_dict(st, s.box ? s.box->errors.load() : 0);
      });

  py::class_<PyLcm::Sub, std::shared_ptr<PyLcm::Sub>>(m, "LCMSubscription")
      .def("set_queue_capacity", [](PyLcm::Sub& s, std::size_t n) { s.capacity = n; })
      .def_property_readonly("dropped", [](PyLcm::Sub& s) { return s.dropped.load(); });

  py::class_<PyLcm, std::shared_ptr<PyLcm>>(m, "_LCM")
      .def(py::init([](std::shared_ptr<PyRuntime> runtime) {
        auto l = std::make_shared<PyLcm>();
        l->runtime = std::move(runtime);
        l->node.emplace(l->runtime->get().create_node("lcm"));
        l->runtime->adopt(l);
        return l;
      }))
      .def("close", &PyLcm::close)
      .def("publish", &PyLcm::publish, py::arg("channel"), py::arg("data"))
      .def("subscribe", &PyLcm::subscribe, py::arg("channel"), py::arg("handler"))
      .def("unsubscribe", &PyLcm::unsubscribe, py::arg("subscription"))
      .def("handle", [](PyLcm& l, std::optional<double> timeout) { return l.handle(timeout); },
           py::arg("timeout") = py::none())
      .def("fileno", [](PyLcm& l) { return l.efd; });

  m.def("_current_runtime", []() -> std::shared_ptr<PyRuntime> {
    auto r = g_runtime.lock();
    return r && r->rt ? r : nullptr;
  });
  m.def("_close_all", &close_all);
}
