// The aligator side of bench/aligator_compare.py: our OCPs transcribed into aligator, solved by SolverProxDDP.
//
//   proxddp_solve check  DIR        cost and every x_{t+1} of DIR/check.txt's (X, U), written to DIR/check_out.txt
//   proxddp_solve solve  DIR TOL MU_INIT ROLLOUT MAX_ITERS   (ROLLOUT: linear | nonlinear)
//                                   every instance of DIR/instances.txt from its guess; DIR/solve_out.txt
//
// The task's Pinocchio model is built as sdp_cli.tasks builds it: the pendulums by aligator's create_pendulum
// (sdp_cli.tasks.pendulum.create_pendulum, constants from DIR/problem.txt), UR5 and the quadrotor from the same
// example-robot-data URDF file (its path in DIR/problem.txt; the quadrotor with a free-flyer root joint). The
// transcription check (mode check) is what says the two models are the same. DIR/problem.txt names the task
// and its constants. Files are "key v1 v2 ..." lines, doubles written with 17
// significant digits, so both sides read exactly what the other wrote. Transcriptions (bench/aligator_compare.py's
// docstring says why each term is exact):
//   pendulum, double_pendulum: running dt 1/2 (W_GOAL ||ee - goal||^2 + W_U ||u||^2), terminal 1/2 W_GOAL_T ||ee - goal||^2
//   ur5-*: running dt 1/2 (W_Q ||q||^2 + W_V ||v||^2 + W_U ||u - g(q)||^2 + W_EE ||ee - p||^2),
//          terminal 1/2 (W_EE_T ||ee - p||^2 + W_TWIST_T ||twist_LWA||^2 + W_X_T ||x||^2)
//   quadrotor-0: running dt 1/2 (W_P ||p - p_goal||^2 + W_ROT ||2 q_vec||^2 + W_V ||v||^2 + W_U ||u - u_hover||^2),
//          terminal the state terms x W_TERMINAL plus 1/2 (W_P_ARRIVE ||p - p_goal||^2 + W_V_ARRIVE ||v||^2);
//          z_floor <= z <= z_ceil on x_0..x_T (x_0 satisfies it)
// Dynamics: semi-implicit Euler of Pinocchio's ABA with tau = B u (B = the task's actuation matrix); controls
// boxed u_lb <= u <= u_ub as a stage constraint.
#include <aligator/core/stage-data.hpp>
#include <aligator/core/stage-model.hpp>
#include <aligator/core/traj-opt-data.hpp>
#include <aligator/core/traj-opt-problem.hpp>
#include <aligator/core/unary-function.hpp>
#include <aligator/modelling/constraints/box-constraint.hpp>
#include <aligator/modelling/constraints/negative-orthant.hpp>
#include <aligator/modelling/costs/quad-residual-cost.hpp>
#include <aligator/modelling/costs/sum-of-costs.hpp>
#include <aligator/modelling/dynamics/integrator-semi-euler.hpp>
#include <aligator/modelling/dynamics/multibody-free-fwd.hpp>
#include <aligator/modelling/multibody/frame-translation.hpp>
#include <aligator/modelling/multibody/frame-velocity.hpp>
#include <aligator/modelling/multibody/gravity-compensation-residual.hpp>
#include <aligator/modelling/spaces/multibody.hpp>
#include <aligator/modelling/state-error.hpp>
#include <aligator/solvers/proxddp/solver-proxddp.hpp>

#include <pinocchio/algorithm/frames.hpp>
#include <pinocchio/multibody/model.hpp>
#include <pinocchio/parsers/urdf.hpp>

#include <cstdlib>
#include <ctime>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

using Eigen::MatrixXd;
using Eigen::VectorXd;
using Model = pinocchio::ModelTpl<double>;
using Space = aligator::MultibodyPhaseSpace<double>;
using Cost = aligator::CostAbstractTpl<double>;
using CostStack = aligator::CostStackTpl<double>;
using QuadCost = aligator::QuadraticResidualCostTpl<double>;
using Stage = aligator::StageModelTpl<double>;
using Problem = aligator::TrajOptProblemTpl<double>;
using Data = aligator::StageFunctionDataTpl<double>;
template <class T> using poly = xyz::polymorphic<T>;

// ------------------------------------------------------------------ key-value files
using KV = std::map<std::string, std::vector<double>>;

KV read_kv(const std::string &path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot read " + path);
  KV out;
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream s(line);
    std::string key, tok;
    if (!(s >> key) || key == "task") continue;   // "task NAME": the one line that is not numbers
    std::vector<double> v;
    while (s >> tok) v.push_back(std::stod(tok));   // stod reads "nan" / "inf" too
    out[key] = v;
  }
  return out;
}

const std::vector<double> &need(const KV &kv, const std::string &key) {
  auto it = kv.find(key);
  if (it == kv.end()) throw std::runtime_error("missing key " + key);
  return it->second;
}

VectorXd vec(const KV &kv, const std::string &key) {
  const auto &v = need(kv, key);
  return Eigen::Map<const VectorXd>(v.data(), (Eigen::Index)v.size());
}

double num(const KV &kv, const std::string &key) { return need(kv, key).at(0); }

std::vector<VectorXd> rows(const KV &kv, const std::string &key, int n) {
  VectorXd flat = vec(kv, key);
  if (flat.size() % n) throw std::runtime_error(key + ": size not a multiple of the row length");
  std::vector<VectorXd> out;
  for (Eigen::Index i = 0; i < flat.size() / n; ++i) out.push_back(flat.segment(i * n, n));
  return out;
}

void put(std::ostream &o, const std::string &key, const VectorXd &v) {
  o << key;
  for (Eigen::Index i = 0; i < v.size(); ++i) o << ' ' << v[i];
  o << '\n';
}

void put(std::ostream &o, const std::string &key, const std::vector<VectorXd> &vs) {
  o << key;
  for (const auto &v : vs)
    for (Eigen::Index i = 0; i < v.size(); ++i) o << ' ' << v[i];
  o << '\n';
}

// ------------------------------------------------------------------ residuals aligator does not have
// For a free-flyer state x = (p, quat (x, y, z, w), v), tangent dx = (dp_body, dtheta_body, dv): the base
// position p, the vector 2 q_vec and the body twist v. Their Jacobians in the tangent of q (+) dq:
// d p / d dp_body = R; d q_vec / d dtheta = 1/2 (q_w I + [q_vec]x) (right perturbation q (x) exp(dtheta / 2)).
struct BasePosition : aligator::UnaryFunctionTpl<double> {
  ALIGATOR_UNARY_FUNCTION_INTERFACE(double);
  Eigen::Vector3d target;
  Eigen::VectorXi rows_;   // which coordinates of p - target to keep
  BasePosition(int ndx, int nu, const Eigen::Vector3d &t, Eigen::VectorXi keep)
      : Base(ndx, nu, (int)keep.size()), target(t), rows_(keep) {}
  void evaluate(const ConstVectorRef &x, Data &d) const override {
    Eigen::Vector3d e = x.head<3>() - target;
    for (int i = 0; i < rows_.size(); ++i) d.value_[i] = e[rows_[i]];
  }
  void computeJacobians(const ConstVectorRef &x, Data &d) const override {
    Eigen::Quaterniond q(x[6], x[3], x[4], x[5]);
    Eigen::Matrix3d R = q.toRotationMatrix();
    d.Jx_.setZero();
    for (int i = 0; i < rows_.size(); ++i) d.Jx_.block(i, 0, 1, 3) = R.row(rows_[i]);
  }
};

struct QuatVec : aligator::UnaryFunctionTpl<double> {
  ALIGATOR_UNARY_FUNCTION_INTERFACE(double);
  QuatVec(int ndx, int nu) : Base(ndx, nu, 3) {}
  void evaluate(const ConstVectorRef &x, Data &d) const override { d.value_ = 2.0 * x.segment<3>(3); }
  void computeJacobians(const ConstVectorRef &x, Data &d) const override {
    Eigen::Vector3d qv = x.segment<3>(3);
    Eigen::Matrix3d S;
    S << 0, -qv[2], qv[1], qv[2], 0, -qv[0], -qv[1], qv[0], 0;
    d.Jx_.setZero();
    d.Jx_.block<3, 3>(0, 3) = x[6] * Eigen::Matrix3d::Identity() + S;   // 2 * 1/2 (q_w I + [q_vec]x)
  }
};

struct Velocity : aligator::UnaryFunctionTpl<double> {
  ALIGATOR_UNARY_FUNCTION_INTERFACE(double);
  int nq, nv;
  Velocity(int nq_, int nv_, int nu) : Base(2 * nv_, nu, nv_), nq(nq_), nv(nv_) {}
  void evaluate(const ConstVectorRef &x, Data &d) const override { d.value_ = x.tail(nv); }
  void computeJacobians(const ConstVectorRef &, Data &d) const override {
    d.Jx_.setZero();
    d.Jx_.rightCols(nv).setIdentity();
  }
};

// ------------------------------------------------------------------ the problem
struct Ocp {
  Model model;
  std::string task;
  int T = 0, nu = 0;
  double dt = 0;
  MatrixXd actuation;
  VectorXd u_lb, u_ub;
  KV kv;
};

Ocp load(const std::string &dir) {
  Ocp o;
  o.kv = read_kv(dir + "/problem.txt");
  std::ifstream in(dir + "/problem.txt");
  std::string key, urdf;
  in >> key >> o.task;   // first line: "task NAME"
  std::ifstream names(dir + "/urdf.txt");
  if (names >> urdf) {   // "PATH [free_flyer]"
    std::string ff;
    if (names >> ff && ff == "free_flyer")
      pinocchio::urdf::buildModel(urdf, pinocchio::JointModelFreeFlyer(), o.model);
    else
      pinocchio::urdf::buildModel(urdf, o.model);
  } else {   // aligator's create_pendulum(N), as sdp_cli.tasks.pendulum builds it
    const int n_links = (int)num(o.kv, "n_links");
    const double mass = num(o.kv, "body_mass"), radius = num(o.kv, "body_radius"), length = num(o.kv, "link_length");
    pinocchio::JointIndex parent = 0;
    pinocchio::SE3 placement = pinocchio::SE3::Identity();
    pinocchio::SE3 body(Eigen::Matrix3d::Identity(), Eigen::Vector3d(0, 0, length));
    for (int k = 0; k < n_links; ++k) {
      auto joint = o.model.addJoint(parent, pinocchio::JointModelRX(), placement, "joint_" + std::to_string(k + 1));
      o.model.appendBodyToJoint(joint, pinocchio::Inertia::FromSphere(mass, radius), body);
      parent = joint;
      placement = body;
    }
    o.model.addFrame(pinocchio::Frame("end_effector", parent, 0, body, pinocchio::OP_FRAME));
  }
  o.T = (int)num(o.kv, "T");
  o.dt = num(o.kv, "dt");
  o.u_lb = vec(o.kv, "u_lb");
  o.u_ub = vec(o.kv, "u_ub");
  o.nu = (int)o.u_lb.size();
  VectorXd act = vec(o.kv, "actuation");
  if (act.size() != o.model.nv * o.nu) throw std::runtime_error("actuation: expected nv x nu entries");
  o.actuation = Eigen::Map<const MatrixXd>(act.data(), o.model.nv, o.nu);   // column-major
  return o;
}

MatrixXd eye(int n, double w) { return w * MatrixXd::Identity(n, n); }

// xi: the instance's parameters (x0, then the task's target if any), as the Python side writes them
Problem build(const Ocp &o, const VectorXd &x0, const VectorXd &target) {
  Space space(o.model);
  const int ndx = space.ndx(), nu = o.nu, nq = o.model.nq, nv = o.model.nv;
  const double dt = o.dt;
  aligator::dynamics::MultibodyFreeFwdDynamicsTpl<double> ode(space, o.actuation);
  aligator::dynamics::IntegratorSemiImplEulerTpl<double> dyn(ode, dt);
  CostStack run(space, nu), term(space, nu);
  const KV &kv = o.kv;
  using FrameTranslation = aligator::FrameTranslationResidualTpl<double>;
  using ControlError = aligator::ControlErrorResidualTpl<double>;
  std::vector<std::pair<poly<aligator::StageFunctionTpl<double>>, poly<aligator::ConstraintSetTpl<double>>>> state_cstr;
  if (o.task == "pendulum" || o.task == "double_pendulum") {
    auto frame = (pinocchio::FrameIndex)num(kv, "frame");
    Eigen::Vector3d goal = vec(kv, "goal");
    run.addCost(QuadCost(space, FrameTranslation(ndx, nu, o.model, goal, frame), eye(3, dt * num(kv, "W_GOAL"))));
    run.addCost(QuadCost(space, ControlError(ndx, VectorXd::Zero(nu)), eye(nu, dt * num(kv, "W_U"))));
    term.addCost(QuadCost(space, FrameTranslation(ndx, nu, o.model, goal, frame), eye(3, num(kv, "W_GOAL_T"))));
  } else if (o.task.rfind("ur5", 0) == 0) {
    auto frame = (pinocchio::FrameIndex)num(kv, "frame");
    Eigen::Vector3d p = target;
    VectorXd w_x(ndx);
    w_x << VectorXd::Constant(nv, dt * num(kv, "W_Q")), VectorXd::Constant(nv, dt * num(kv, "W_V"));
    VectorXd x_ref = VectorXd::Zero(nq + nv);
    run.addCost(QuadCost(space, aligator::StateErrorResidualTpl<double>(space, nu, x_ref), MatrixXd(w_x.asDiagonal())));
    run.addCost(QuadCost(space, aligator::GravityCompensationResidualTpl<double>(ndx, o.model), eye(nu, dt * num(kv, "W_U"))));
    run.addCost(QuadCost(space, FrameTranslation(ndx, nu, o.model, p, frame), eye(3, dt * num(kv, "W_EE"))));
    term.addCost(QuadCost(space, FrameTranslation(ndx, nu, o.model, p, frame), eye(3, num(kv, "W_EE_T"))));
    term.addCost(QuadCost(space, aligator::FrameVelocityResidualTpl<double>(ndx, nu, o.model, pinocchio::Motion::Zero(),
                                                                           frame, pinocchio::LOCAL_WORLD_ALIGNED),
                          eye(6, num(kv, "W_TWIST_T"))));
    term.addCost(QuadCost(space, aligator::StateErrorResidualTpl<double>(space, nu, x_ref), eye(ndx, num(kv, "W_X_T"))));
  } else if (o.task == "quadrotor-0") {
    Eigen::Vector3d goal = target;
    Eigen::VectorXi xyz(3), z(1);
    xyz << 0, 1, 2;
    z << 2;
    const double wp = num(kv, "W_P"), wr = num(kv, "W_ROT"), wv = num(kv, "W_V"), wt = num(kv, "W_TERMINAL");
    run.addCost(QuadCost(space, BasePosition(ndx, nu, goal, xyz), eye(3, dt * wp)));
    run.addCost(QuadCost(space, QuatVec(ndx, nu), eye(3, dt * wr)));
    run.addCost(QuadCost(space, Velocity(nq, nv, nu), eye(nv, dt * wv)));
    run.addCost(QuadCost(space, ControlError(ndx, vec(kv, "u_hover")), eye(nu, dt * num(kv, "W_U"))));
    term.addCost(QuadCost(space, BasePosition(ndx, nu, goal, xyz), eye(3, wt * wp + num(kv, "W_P_ARRIVE"))));
    term.addCost(QuadCost(space, QuatVec(ndx, nu), eye(3, wt * wr)));
    term.addCost(QuadCost(space, Velocity(nq, nv, nu), eye(nv, wt * wv + num(kv, "W_V_ARRIVE"))));
    // z in [z_floor, z_ceil]: the height residual z - 0 in a box
    Eigen::Vector3d zero = Eigen::Vector3d::Zero();
    VectorXd lo(1), hi(1);
    lo << num(kv, "z_floor");
    hi << num(kv, "z_ceil");
    state_cstr.emplace_back(BasePosition(ndx, nu, zero, z), aligator::BoxConstraintTpl<double>(lo, hi));
  } else {
    throw std::runtime_error("no transcription of task " + o.task);
  }
  Stage stage(run, dyn);
  stage.addConstraint(ControlError(ndx, VectorXd::Zero(nu)), aligator::BoxConstraintTpl<double>(o.u_lb, o.u_ub));
  for (auto &c : state_cstr) stage.addConstraint(c.first, c.second);
  std::vector<poly<Stage>> stages(o.T, stage);
  Problem problem(x0, stages, term);
  for (auto &c : state_cstr) problem.addTerminalConstraint(c.first, c.second);
  return problem;
}

double cpu_seconds() {
  timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

int main(int argc, char **argv) {
  try {
    if (argc < 3) throw std::runtime_error("usage: proxddp_solve check|solve DIR [TOL MU_INIT ROLLOUT MAX_ITERS]");
    const std::string mode = argv[1], dir = argv[2];
    Ocp o = load(dir);
    const int nx = o.model.nq + o.model.nv;
    std::cout << std::setprecision(17);
    if (mode == "check") {
      KV in = read_kv(dir + "/check.txt");
      auto xs = rows(in, "X", nx);
      auto us = rows(in, "U", o.nu);
      Problem problem = build(o, xs[0], vec(in, "target"));
      aligator::TrajOptDataTpl<double> data(problem);
      double cost = problem.evaluate(xs, us, data);
      std::vector<VectorXd> xnext;
      for (int t = 0; t < o.T; ++t) {
        auto &dd = *data.stage_data[t]->dynamics_data;
        xnext.push_back(dd.xnext_);
      }
      std::ofstream out(dir + "/check_out.txt");
      out << std::setprecision(17);
      out << "cost " << cost << '\n';
      put(out, "xnext", xnext);
      return 0;
    }
    if (mode != "solve" || argc != 7) throw std::runtime_error("usage: proxddp_solve solve DIR TOL MU_INIT ROLLOUT MAX_ITERS");
    const double tol = std::stod(argv[3]), mu_init = std::stod(argv[4]);
    const std::string rollout = argv[5];
    const std::size_t max_iters = (std::size_t)std::stoul(argv[6]);
    KV in = read_kv(dir + "/instances.txt");
    const int n = (int)num(in, "n");
    std::ofstream out(dir + "/solve_out.txt");
    out << std::setprecision(17);
    for (int i = 0; i < n; ++i) {
      const std::string k = "i" + std::to_string(i) + ".";
      auto xs = rows(in, k + "X", nx);
      auto us = rows(in, k + "U", o.nu);
      Problem problem = build(o, vec(in, k + "x0"), vec(in, k + "target"));
      aligator::SolverProxDDPTpl<double> solver(tol, mu_init, max_iters,
                                                std::getenv("SDP_PROXDDP_VERBOSE") ? aligator::VERBOSE : aligator::QUIET);
      solver.rollout_type_ = rollout == "nonlinear" ? aligator::RolloutType::NONLINEAR : aligator::RolloutType::LINEAR;
      solver.setNumThreads(1);
      double t0 = cpu_seconds();
      solver.setup(problem);
      bool conv = solver.run(problem, xs, us);
      double cpu = cpu_seconds() - t0;
      const auto &r = solver.results_;
      out << k << "conv " << (conv ? 1 : 0) << '\n'
          << k << "iters " << r.num_iters << '\n'
          << k << "al_iters " << r.al_iter << '\n'
          << k << "cost " << r.traj_cost_ << '\n'
          << k << "prim_infeas " << r.prim_infeas << '\n'
          << k << "dual_infeas " << r.dual_infeas << '\n'
          << k << "cpu " << cpu << '\n';
      put(out, k + "X", r.xs);
      put(out, k + "U", r.us);
    }
    return 0;
  } catch (const std::exception &e) {
    std::cerr << "proxddp_solve: " << e.what() << '\n';
    return 1;
  }
}
