// Actions over raw bytes (typed in python/lcmx/__init__.py): _ActionServer and the goal handle
// its execute gets (_ActionGoal), _ActionClient and the goals it sends (_ClientGoal), and
// Node.create_action_server_raw / Node.create_action_client_raw.
#include <shared_mutex>

#include "binding.hpp"

namespace lcmxpy {
namespace {

// None: raw bytes; else (goal, feedback, result names, then their fingerprints).
lcmx::detail::ActionTypes action_types(const py::object& t) {
  if (t.is_none()) return {};
  auto v = t.cast<std::tuple<std::string, std::string, std::string, std::int64_t, std::int64_t, std::int64_t>>();
  return {std::get<0>(v), std::get<1>(v), std::get<2>(v), std::get<3>(v), std::get<4>(v), std::get<5>(v)};
}

py::tuple to_tuple(const lcmx::GoalStatus& s) {
  return py::make_tuple(s.goal_id, lcmx::to_string(s.state), s.message);
}

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

}  // namespace

void bind_actions(py::module_& m, NodeClass& node) {
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

  node.def("create_action_server_raw", &create_action_server, py::arg("name"), py::arg("execute"),
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
           py::arg("name"), py::arg("types") = py::none());
}

}  // namespace lcmxpy
