// ScrewVertebra: rigid anchor screw (6 DOF) in a rigidly fixed C4 vertebra, joined by the diagonal
// spring-damper matrix force element of Kramer and Bauer (eq. 1, Sections 2.1-2.3, Table 1), with the
// optional axial effects beyond eq. 1 of fmu/MODEL.md (the candidates of `fmusa diagnose`).
//
// This is the Modelica statement of fmu/MODEL.md and the one source of the FMU's equations and variables:
// `make fmu` translates the equation section into C (fmu/codegen.py: pymoca, CasADi), which the FMU's
// solver (fmu/solver.c) integrates. Its public variables (names, types, causalities, units, defaults,
// descriptions) are the FMU's variable contract: fmu/generate.py derives modelDescription.xml and
// variables.h from them (value references in declaration order), and tests/test_modelica.py checks the
// result against pymoca's reading of this file. Entry k of the arrays tab_y and tab_F is the FMU variable
// tab_y[k] / tab_F[k] with description "<description> k".
//
// Frames: V is fixed to the vertebra (origin at the vertebra's interaction point, y = screw axis out of
// the bone, the pullout direction). S is fixed to the screw (origin at the head centre H, y along the
// screw axis towards the head). At rest S is parallel to V and the screw's interaction point P
// coincides with the vertebra's. Coordinates q = (x, y, z, alpha, beta, gamma): (x, y, z) is the
// displacement of P in V, (alpha, beta, gamma) are Cardan angles, R = Rx(alpha)*Ry(beta)*Rz(gamma)
// maps S to V (singular at beta = +-pi/2).
//
// Assumptions (not given by the paper):
//  - Principal moments of inertia: a solid cylinder of length L_screw and diameter D_screw with the
//    screw's mass, I_1 = I_3 = m*(3*r^2 + L^2)/12, I_2 = m*r^2/2 (r = D_screw/2). Table 1 gives only
//    the principal directions: e1 = (1, 0, 0), e2 = (0, 0.96, 0.28), e3 = (0, -0.28, 0.96) in S,
//    i.e. a tilt phi_inertia = atan2(0.28, 0.96) about x; the inertia tensor about the centre of
//    gravity is I_B = Q*diag(I_1, I_2, I_3)*Q^T with Q = Rx(phi_inertia).
//  - No gravity (0.29 g weighs 2.8 mN against a 411 N pull).
//  - The rotational stiffness and damping defaults (c_alpha, c_beta, c_gamma, d_alpha, d_beta,
//    d_gamma) are assumptions: the paper gives no values.
//  - The rotational part of eq. 1 acts on the Cardan angles as generalised forces
//    Q_I = -(c_k*theta_k + d_k*der(theta_k)); the body torque tau_I satisfies G^T*tau_I = Q_I.
//  - The translational force of eq. 1 acts on the screw at P; the pullout force at H along V's y axis.
//  - With unload = true the pullout force falls linearly from F_max at t_unload (>= t_ramp) to 0 at
//    t_unload + t_ramp; it is 0 before time 0.
//
// Effects beyond eq. 1 (fmu/MODEL.md, section of that name): extensions of the axial interface force
// only, each switched off by its parameters' defaults, so eq. 1 is nested in every one. With
// w = smooth_w, S(u) = w*log(1 + exp(u/w)) (softplus: max(u, 0) with the corner rounded over w) and
// sigma(u) = dS/du:
//  - backlash gap: elastic displacement y_e = S(y - gap) - S(-y - gap), v_e = (sigma(y - gap) +
//    sigma(-y - gap))*v_y (y_e = y, v_e = v_y exactly when gap = 0);
//  - spring F_s = yield_ratio*F_el + (1 - yield_ratio)*yield_F*z_y + (nl_ratio - 1)*c_y*(S(y_e -
//    nl_y_b) - S(-y_e - nl_y_b)), F_el = c_y*y_e or the table force at y_e (bilinear stiffness past
//    +-nl_y_b; yield softening);
//  - Bouc-Wen states with n = 4, 0 at the start: der(z_y) = (v_e/y_Y)*(1 - H(z_y*v_e)*z_y^4),
//    y_Y = yield_F/c_y (yield), and der(z_f) = (v_y/fric_x)*(1 - H(z_f*v_y)*z_f^4), F_fric = fric_F*z_f
//    (Coulomb friction with pre-sliding); H(x) = 1 for x > 0, else 0;
//  - Maxwell branch, 0 at the start: der(F_ve) = ve_k*v_y - F_ve/ve_tau;
//  - interface damage (dmg_rate > 0): kappa, 0 at the start, follows the largest |y_e| reached,
//    der(kappa) = max(0, sign(y_e)*v_e)*sigma(|y_e| - kappa); D = 1 - exp(-dmg_rate*S(kappa - dmg_y0));
//    the spring becomes (1 - D)*F_s + D*dmg_F_res*y_e/(dmg_y0 + S(kappa - dmg_y0)) (a softening to the
//    residual force, unloading and reloading on the secant to the origin);
//  - total axial force F_y = F_s + d_y*v_y + F_fric + F_ve; measured outputs F_meas = F_pull + F_offset,
//    y_meas = y + y_offset (sensor bias, the physics is unchanged).
//  As in the FMU, the states z_y and z_f keep a zero rate while their effect is off.
//
// Differences to the FMU that are inherent to a Modelica tool:
//  - rtol, h_max, monitors, max_steps and max_wall_s are the FMU's solver settings; a Modelica tool ignores
//    them (set the tolerance in the simulation setup, see the experiment annotation).
//  - n_steps (the FMU's count of internal solver steps) stays 0 here.
//  - Inputs are used as given; the FMU extrapolates them inside a communication step with the
//    derivatives set by fmi2SetRealInputDerivatives. In motion-driven mode with use_y_in = true the
//    tool differentiates y_in twice (index reduction), so y_in must come from a smooth source.
//  - The Bouc-Wen switch H(z*v) is written with noEvent inside smooth(0, ...): the rates of z_y and z_f
//    are continuous in z and v, so no event is needed (the FMU's solver does not locate the switch
//    either). The effect states z_y, z_f, F_ve are states of the Modelica model (protected z_y, z_f;
//    output F_ve) and kappa (protected); the FMU carries them as its solver states 13-16.
//  - The FMU's generated code leaves out the asserts (fmu/model.c validates the parameters before any
//    run, with messages that name the fix) and the monitors (its solver computes them between steps).
//    The drive constraint of the motion-driven mode is differentiated twice by the generator, with the
//    inputs linear within a communication step (so der(v_y) = 0 there), as a tool's index reduction does.

// Functions of the model, at the top level of the file: the generator (fmu/codegen.py) names a function
// by a plain identifier, so they cannot be nested in the model.
function ScrewVertebraSoftplus
  "S(u) = w*log(1 + exp(u/w)): max(u, 0) with the corner rounded over w (written so that exp cannot overflow)"
  input Real u;
  input Real w "Rounding width, > 0";
  output Real S;
algorithm
  S := max(u, 0) + w*log(1 + exp(-abs(u)/w));
  annotation(smoothOrder=1);
end ScrewVertebraSoftplus;

function ScrewVertebraSoftplusSlope
  "sigma(u) = dS/du = 1/(1 + exp(-u/w)) of ScrewVertebraSoftplus (written so that exp cannot overflow)"
  input Real u;
  input Real w "Rounding width, > 0";
  output Real sigma;
algorithm
  sigma := exp(-max(-u, 0)/w)/(1 + exp(-abs(u)/w));
  annotation(smoothOrder=1);
end ScrewVertebraSoftplusSlope;

model ScrewVertebra
  "Rigid pedicle/anchor screw (6 DOF) in a fixed C4 vertebra joined by a diagonal spring-damper matrix force element (Kramer and Bauer, eq. 1)"

  // Mass properties (Table 1)
  parameter Real m(unit="kg") = 0.00029 "Mass of the screw (Table 1)";
  parameter Real L_screw(unit="m") = 0.017 "Screw length from head to tip (Table 1)";
  parameter Real D_screw(unit="m") = 0.0027 "Screw diameter (Table 1)";
  parameter Real cg_x(unit="m") = 0 "Centre of gravity x in the screw frame (origin at the head centre)";
  parameter Real cg_y(unit="m") = -0.00703 "Centre of gravity y in the screw frame (Table 1)";
  parameter Real cg_z(unit="m") = 0 "Centre of gravity z in the screw frame";
  parameter Real phi_inertia(unit="rad") = atan2(0.28, 0.96) "Tilt of the principal axes of inertia about x (Table 1: cos 0.96 / sin 0.28)";
  final parameter Real I_1(unit="kg.m2") = m*(3*(D_screw/2)^2 + L_screw^2)/12 "Principal moment about axis 1 (solid cylinder: m*(3*r^2+L^2)/12)";
  final parameter Real I_2(unit="kg.m2") = m*(D_screw/2)^2/2 "Principal moment about axis 2 near the screw axis (solid cylinder: m*r^2/2)";
  final parameter Real I_3(unit="kg.m2") = m*(3*(D_screw/2)^2 + L_screw^2)/12 "Principal moment about axis 3 (solid cylinder: m*(3*r^2+L^2)/12)";

  // Interaction point P on the screw
  parameter Real rI_x(unit="m") = 0 "Interaction point on the screw x in the screw frame";
  parameter Real rI_y(unit="m") = -0.00703 "Interaction point on the screw y in the screw frame";
  parameter Real rI_z(unit="m") = 0 "Interaction point on the screw z in the screw frame";

  // Matrix force element (eq. 1), diagonal
  parameter Real c_x(unit="N/m") = 823224 "Interface stiffness along x (eq. 1)";
  parameter Real c_y(unit="N/m") = 823224 "Interface stiffness along the screw axis y (eq. 1)";
  parameter Real c_z(unit="N/m") = 823224 "Interface stiffness along z (eq. 1)";
  parameter Real c_alpha(unit="N.m/rad") = 10 "Interface rotational stiffness about x (eq. 1)";
  parameter Real c_beta(unit="N.m/rad") = 1 "Interface rotational stiffness about y (eq. 1)";
  parameter Real c_gamma(unit="N.m/rad") = 10 "Interface rotational stiffness about z (eq. 1)";
  parameter Real d_x(unit="N.s/m") = 488 "Interface damping along x (eq. 1)";
  parameter Real d_y(unit="N.s/m") = 488 "Interface damping along the screw axis y (eq. 1)";
  parameter Real d_z(unit="N.s/m") = 488 "Interface damping along z (eq. 1)";
  parameter Real d_alpha(unit="N.m.s/rad") = 0.01 "Interface rotational damping about x (eq. 1)";
  parameter Real d_beta(unit="N.m.s/rad") = 0.01 "Interface rotational damping about y (eq. 1)";
  parameter Real d_gamma(unit="N.m.s/rad") = 0.01 "Interface rotational damping about z (eq. 1)";

  // Load case
  parameter Integer mode = 1 "1: force-driven pullout; 2: motion-driven (axial displacement prescribed)"
    annotation(Evaluate=true);
  parameter Real F_max(unit="N") = 411 "Peak pullout force at the screw head along y";
  parameter Real t_ramp(unit="s") = 10 "Duration of the linear force ramp from 0 to F_max";
  parameter Boolean unload = false "Unload linearly to 0 over t_ramp starting at t_unload";
  parameter Real t_unload(unit="s") = 20 "Start of unloading (used when unload is true)";
  parameter Real v_pull(unit="m/s") = 2e-3/60 "Motion-driven pull velocity when use_y_in is false (2 mm/min)";
  parameter Boolean use_y_in = false "Motion-driven: follow input y_in (with its derivative) instead of v_pull*time"
    annotation(Evaluate=true);

  // Optional axial force-displacement table replacing c_y*y
  parameter Integer tab_n = 0 "Points in the axial force-displacement table (0: linear c_y; otherwise 2..16)";
  parameter Real tab_y[16](each unit="m") = zeros(16) "Axial force-displacement table: displacement";
  parameter Real tab_F[16](each unit="N") = zeros(16) "Axial force-displacement table: force";

  // Equilibrium monitor (Table 2)
  parameter Real eps_v_eq(unit="m/s") = 5e-08 "Equilibrium threshold on |v_y| (Table 2)";
  parameter Real eps_a_eq(unit="m/s2") = 5e-09 "Equilibrium threshold on |a_y| (Table 2)";

  // Solver settings of the FMU: a Modelica tool ignores them
  parameter Real rtol = 1e-06 "Relative local error tolerance for the nonlinear dynamics (the linear element is exact); the monitors follow the closed form of the axial oscillator to rtol, or with a table, an effect or motion drive dense output to the smaller of 1e-7 and 100 rtol";
  parameter Real h_max(unit="s") = 0 "Largest internal step (0: no limit beyond the communication step)";
  parameter Boolean monitors = true "Follow the monitors (y_max, v_y_max, y_mean, v_y_mean, t_eq) between steps; false skips the dense-output checks: faster, and the monitors read NaN";
  parameter Integer max_steps = 1000000 "Work budget: the most internal solver steps (taken or rejected) in one doStep; past it fmi2DoStep returns fmi2Error saying why";
  parameter Real max_wall_s(unit="s") = 0 "Work budget: the most seconds of computing in one doStep (0: no limit); past it fmi2DoStep returns fmi2Error saying why";

  // Effects beyond eq. 1 (fmu/MODEL.md): the defaults switch them off
  parameter Real gap(unit="m") = 0 "Backlash: axial slack, no spring force while |y| < gap (0: off)";
  parameter Real nl_ratio(unit="1") = 1 "Nonlinear stiffness: axial stiffness past the breakpoint divided by c_y (1: off)";
  parameter Real nl_y_b(unit="m") = 0.0005 "Nonlinear stiffness: breakpoint displacement";
  parameter Real yield_ratio(unit="1") = 1 "Yield: post-yield axial stiffness divided by c_y (1: off)";
  parameter Real yield_F(unit="N") = 100 "Yield: axial force at which the interface yields";
  parameter Real fric_F(unit="N") = 0 "Coulomb friction: sliding force opposing axial motion (0: off)";
  parameter Real fric_x(unit="m") = 1e-05 "Coulomb friction: pre-sliding displacement";
  parameter Real ve_k(unit="N/m") = 0 "Viscoelastic relaxation: stiffness of the Maxwell branch (0: off)";
  parameter Real ve_tau(unit="s") = 1 "Viscoelastic relaxation: relaxation time of the Maxwell branch";
  parameter Real F_offset(unit="N") = 0 "Sensor offset: bias added to the measured force F_meas";
  parameter Real y_offset(unit="m") = 0 "Sensor offset: bias added to the measured displacement y_meas";
  parameter Real smooth_w(unit="m") = 1e-06 "Width over which the corners of the gap and the breakpoint are rounded";
  parameter Real dmg_rate(unit="1/m") = 0 "Interface damage: softening rate per metre of displacement past the onset, D = 1 - exp(-dmg_rate*(kappa - dmg_y0)) (0: off)";
  parameter Real dmg_y0(unit="m") = 0.0005 "Interface damage: onset displacement (the largest |y| reached before damage starts)";
  parameter Real dmg_F_res(unit="N") = 0 "Interface damage: residual force of the fully damaged interface (friction plateau)";

  // Inputs
  input Real F_ext_x(unit="N", start=0) "External force at the screw head along x (vertebra frame)";
  input Real F_ext_y(unit="N", start=0) "External force at the screw head along y (vertebra frame)";
  input Real F_ext_z(unit="N", start=0) "External force at the screw head along z (vertebra frame)";
  input Real T_ext_x(unit="N.m", start=0) "External torque on the screw about x (vertebra frame)";
  input Real T_ext_y(unit="N.m", start=0) "External torque on the screw about y (vertebra frame)";
  input Real T_ext_z(unit="N.m", start=0) "External torque on the screw about z (vertebra frame)";
  input Real y_in(unit="m", start=0) "Prescribed axial displacement in motion-driven mode when use_y_in is true";

  // Outputs: coordinates and their rates
  output Real x(unit="m") "Interaction point displacement x (screw point relative to vertebra point)";
  output Real y(unit="m") "Axial displacement of the screw (pullout positive)";
  output Real z(unit="m") "Interaction point displacement z";
  output Real alpha(unit="rad") "Cardan angle about x";
  output Real beta(unit="rad") "Cardan angle about y";
  output Real gamma(unit="rad") "Cardan angle about z";
  output Real v_x(unit="m/s") "Velocity along x";
  output Real v_y(unit="m/s") "Axial velocity of the screw";
  output Real v_z(unit="m/s") "Velocity along z";
  output Real w_alpha(unit="rad/s") "Rate of alpha";
  output Real w_beta(unit="rad/s") "Rate of beta";
  output Real w_gamma(unit="rad/s") "Rate of gamma";
  output Real a_y(unit="m/s2") "Axial acceleration of the screw";

  // Outputs: element forces with eq. 1's sign, pullout force
  output Real F_x(unit="N") "Interface force along x (c_x*x + d_x*v_x)";
  output Real F_y(unit="N") "Axial interface force (c_y*y + d_y*v_y or table force + d_y*v_y; plus the effects of MODEL.md when switched on)";
  output Real F_z(unit="N") "Interface force along z (c_z*z + d_z*v_z)";
  output Real T_alpha(unit="N.m") "Interface torque (c_alpha*alpha + d_alpha*w_alpha)";
  output Real T_beta(unit="N.m") "Interface torque (c_beta*beta + d_beta*w_beta)";
  output Real T_gamma(unit="N.m") "Interface torque (c_gamma*gamma + d_gamma*w_gamma)";
  output Real F_pull(unit="N") "Axial force on the screw head: the load in force-driven mode or the reaction of the drive in motion-driven mode";

  // Outputs: monitors
  output Real y_max(unit="m") "Monitor: max |y| so far (every internal step and between steps)";
  output Real v_y_max(unit="m/s") "Monitor: max |v_y| so far";
  output Real y_mean(unit="m") "Monitor: time average of y over [0, t]";
  output Real v_y_mean(unit="m/s") "Monitor: time average of |v_y| over [0, t]";
  output Real t_eq(unit="s", start=-1) "Monitor: time since which |v_y| <= eps_v_eq and |a_y| <= eps_a_eq hold; -1 while not at rest";
  discrete output Integer n_steps "Internal solver steps taken so far";

  // Outputs: effects beyond eq. 1
  output Real F_meas(unit="N") "Measured force: F_pull + F_offset";
  output Real y_meas(unit="m") "Measured displacement: y + y_offset";
  output Real F_fric(unit="N") "Friction part of the axial interface force";
  output Real F_ve(unit="N") "Maxwell branch part of the axial interface force";
  output Real dmg_D(unit="1") "Interface damage: the damage variable D (0 undamaged, towards 1 failed)";

protected
  // Written in the subset of Modelica that fmu/codegen.py translates into the FMU's C (pymoca and
  // CasADi): scalars only (no arrays of variables, matrix literals or cross()), explicit inverses where
  // the matrix is known in closed form (G, the inertia tensor), if-expressions rather than when-clauses,
  // no while loops or variable subscripts (the table is a sum of ramps), functions at the top level of the
  // file (CasADi names a function by a plain identifier). smooth() and noEvent() are read as their
  // argument, assert() and the monitors (the when-clauses at the end, computed by the FMU's solver) are
  // left out of the generated code.

  // Geometry in the screw frame S: b from P to the centre of gravity, h from the centre of gravity to H
  final parameter Real b_x(unit="m") = cg_x - rI_x;
  final parameter Real b_y(unit="m") = cg_y - rI_y;
  final parameter Real b_z(unit="m") = cg_z - rI_z;
  final parameter Real h_x(unit="m") = -cg_x;
  final parameter Real h_y(unit="m") = -cg_y;
  final parameter Real h_z(unit="m") = -cg_z;
  // Inertia tensor about the centre of gravity I_B = Q*diag(I_1, I_2, I_3)*transpose(Q), Q = Rx(phi_inertia)
  // (columns e1, e2, e3), and its inverse by cofactors
  final parameter Real c_phi = cos(phi_inertia);
  final parameter Real s_phi = sin(phi_inertia);
  final parameter Real I_xx(unit="kg.m2") = I_1;
  final parameter Real I_xy(unit="kg.m2") = 0;
  final parameter Real I_xz(unit="kg.m2") = 0;
  final parameter Real I_yy(unit="kg.m2") = c_phi^2*I_2 + s_phi^2*I_3;
  final parameter Real I_yz(unit="kg.m2") = c_phi*s_phi*(I_2 - I_3);
  final parameter Real I_zz(unit="kg.m2") = s_phi^2*I_2 + c_phi^2*I_3;
  final parameter Real I_det = I_xx*(I_yy*I_zz - I_yz*I_yz) - I_xy*(I_xy*I_zz - I_yz*I_xz)
    + I_xz*(I_xy*I_yz - I_yy*I_xz);
  final parameter Real J_xx = (I_yy*I_zz - I_yz*I_yz)/I_det "inverse of I_B";
  final parameter Real J_xy = (I_xz*I_yz - I_xy*I_zz)/I_det;
  final parameter Real J_xz = (I_xy*I_yz - I_xz*I_yy)/I_det;
  final parameter Real J_yy = (I_xx*I_zz - I_xz*I_xz)/I_det;
  final parameter Real J_yz = (I_xy*I_xz - I_xx*I_yz)/I_det;
  final parameter Real J_zz = (I_xx*I_yy - I_xy*I_xy)/I_det;
  final parameter Real y_Y(unit="m") = yield_F/c_y "Yield displacement of the Bouc-Wen yield state";
  final parameter Boolean yield_on = yield_ratio < 1 or yield_ratio > 1 "Yield softening switched on";
  // Slopes of the force-displacement table's segments (0 past the tab_n points used)
  final parameter Real tab_s1(unit="N/m") = if tab_n > 1 then (tab_F[2] - tab_F[1])/(tab_y[2] - tab_y[1]) else 0;
  final parameter Real tab_s2(unit="N/m") = if tab_n > 2 then (tab_F[3] - tab_F[2])/(tab_y[3] - tab_y[2]) else 0;
  final parameter Real tab_s3(unit="N/m") = if tab_n > 3 then (tab_F[4] - tab_F[3])/(tab_y[4] - tab_y[3]) else 0;
  final parameter Real tab_s4(unit="N/m") = if tab_n > 4 then (tab_F[5] - tab_F[4])/(tab_y[5] - tab_y[4]) else 0;
  final parameter Real tab_s5(unit="N/m") = if tab_n > 5 then (tab_F[6] - tab_F[5])/(tab_y[6] - tab_y[5]) else 0;
  final parameter Real tab_s6(unit="N/m") = if tab_n > 6 then (tab_F[7] - tab_F[6])/(tab_y[7] - tab_y[6]) else 0;
  final parameter Real tab_s7(unit="N/m") = if tab_n > 7 then (tab_F[8] - tab_F[7])/(tab_y[8] - tab_y[7]) else 0;
  final parameter Real tab_s8(unit="N/m") = if tab_n > 8 then (tab_F[9] - tab_F[8])/(tab_y[9] - tab_y[8]) else 0;
  final parameter Real tab_s9(unit="N/m") = if tab_n > 9 then (tab_F[10] - tab_F[9])/(tab_y[10] - tab_y[9]) else 0;
  final parameter Real tab_s10(unit="N/m") = if tab_n > 10 then (tab_F[11] - tab_F[10])/(tab_y[11] - tab_y[10]) else 0;
  final parameter Real tab_s11(unit="N/m") = if tab_n > 11 then (tab_F[12] - tab_F[11])/(tab_y[12] - tab_y[11]) else 0;
  final parameter Real tab_s12(unit="N/m") = if tab_n > 12 then (tab_F[13] - tab_F[12])/(tab_y[13] - tab_y[12]) else 0;
  final parameter Real tab_s13(unit="N/m") = if tab_n > 13 then (tab_F[14] - tab_F[13])/(tab_y[14] - tab_y[13]) else 0;
  final parameter Real tab_s14(unit="N/m") = if tab_n > 14 then (tab_F[15] - tab_F[14])/(tab_y[15] - tab_y[14]) else 0;
  final parameter Real tab_s15(unit="N/m") = if tab_n > 15 then (tab_F[16] - tab_F[15])/(tab_y[16] - tab_y[15]) else 0;

  // Kinematics
  Real ca "cos(alpha)";
  Real sa "sin(alpha)";
  Real cb "cos(beta)";
  Real sb "sin(beta)";
  Real cg "cos(gamma)";
  Real sg "sin(gamma)";
  Real R_11; Real R_12; Real R_13; Real R_21; Real R_22; Real R_23; Real R_31; Real R_32; Real R_33
    "R = Rx(alpha)*Ry(beta)*Rz(gamma) maps the screw frame S to the vertebra frame V";
  Real om_x(unit="rad/s") "Angular velocity of the screw, in S: omega = G*der({alpha, beta, gamma})";
  Real om_y(unit="rad/s");
  Real om_z(unit="rad/s");
  Real gd_x(unit="rad/s2") "der(G)*der({alpha, beta, gamma})";
  Real gd_y(unit="rad/s2");
  Real gd_z(unit="rad/s2");
  Real omd_x(unit="rad/s2") "Angular acceleration of the screw, in S";
  Real omd_y(unit="rad/s2");
  Real omd_z(unit="rad/s2");

  // Forces and torques
  Real F_H_x(unit="N") "Force on the screw head H, in V";
  Real F_H_y(unit="N");
  Real F_H_z(unit="N");
  Real F_Ib_x(unit="N") "Interface force on the screw at P, in S: transpose(R)*F_I, F_I = -{F_x, F_y, F_z}";
  Real F_Ib_y(unit="N");
  Real F_Ib_z(unit="N");
  Real F_Hb_x(unit="N") "Force on the head, in S";
  Real F_Hb_y(unit="N");
  Real F_Hb_z(unit="N");
  Real tau_x(unit="N.m") "Interface torque in S: tau_I = transpose(inverse(G))*Q_I, Q_I = -{T_alpha, T_beta, T_gamma}";
  Real tau_y(unit="N.m");
  Real tau_z(unit="N.m");
  Real M_x(unit="N.m") "Torque about the centre of gravity, in S, less the gyroscopic term omega x (I_B*omega)";
  Real M_y(unit="N.m");
  Real M_z(unit="N.m");
  Real Iom_x(unit="kg.m2/s") "I_B*omega";
  Real Iom_y(unit="kg.m2/s");
  Real Iom_z(unit="kg.m2/s");
  Real e_x(unit="m/s2") "omega_d x b + omega x (omega x b): acceleration of the centre of gravity relative to P, in S";
  Real e_y(unit="m/s2");
  Real e_z(unit="m/s2");
  Real wb_x(unit="m/s") "omega x b";
  Real wb_y(unit="m/s");
  Real wb_z(unit="m/s");

  // Axial effects
  Real F_spring_y(unit="N") "Axial spring force F_s of the elastic displacement y_e (with the effects)";
  Real F_el(unit="N") "Elastic force c_y*y_e or the table force at y_e";
  Real F_tab(unit="N") "Force of the force-displacement table at y_e";
  Real y_e(unit="m") "Elastic axial displacement after the backlash gap";
  Real v_e(unit="m/s") "Rate of y_e";
  Real z_y(unit="1", start=0) "Bouc-Wen yield state";
  Real z_f(unit="1", start=0) "Bouc-Wen friction state";
  Real kappa(unit="m", start=0) "Largest elastic displacement |y_e| reached (interface damage)";
  Real F_spring_u(unit="N") "Axial spring force before damage";
  Real past(unit="m") "Displacement reached past the onset of damage, softplus(kappa - dmg_y0)";
  Real F_load(unit="N") "Pullout force of the force-driven load case";

  // Monitors (computed by the FMU's solver; here for a Modelica tool)
  discrete Real y_hold(unit="m", start=0, fixed=true) "max |y| at the local maxima of |y| so far";
  discrete Real v_hold(unit="m/s", start=0, fixed=true) "max |v_y| at the local maxima of |v_y| so far";
  Boolean at_rest "|v_y| <= eps_v_eq and |a_y| <= eps_a_eq";
  Real y_int(unit="m.s", start=0, fixed=true) "Integral of y since the start";
  Real v_abs_int(unit="m", start=0, fixed=true) "Integral of |v_y| since the start";
  discrete Real t_rest(unit="s", start=0, fixed=true) "Time at which at_rest last became true";

initial equation
  // Start at rest in the reference configuration
  x = 0;
  z = 0;
  alpha = 0;
  beta = 0;
  gamma = 0;
  v_x = 0;
  v_z = 0;
  w_alpha = 0;
  w_beta = 0;
  w_gamma = 0;
  if mode <> 2 then
    y = 0;
    v_y = 0;
  end if;
  // The states of the effects start at 0
  z_y = 0;
  z_f = 0;
  F_ve = 0;
  kappa = 0;

equation
  assert(mode == 1 or mode == 2, "mode must be 1 (force-driven) or 2 (motion-driven)");
  assert(tab_n == 0 or tab_n >= 2 and tab_n <= 16, "tab_n must be 0 or 2..16");
  assert(not unload or t_unload >= t_ramp, "unloading must start after the ramp (t_unload >= t_ramp)");
  assert(abs(cos(beta)) >= 1e-6, "the Cardan angle beta reached +-pi/2 (gimbal lock)");

  // Kinematics: six generalised coordinates and their rates
  der(x) = v_x;
  der(y) = v_y;
  der(z) = v_z;
  der(alpha) = w_alpha;
  der(beta) = w_beta;
  der(gamma) = w_gamma;
  a_y = der(v_y);
  ca = cos(alpha);
  sa = sin(alpha);
  cb = cos(beta);
  sb = sin(beta);
  cg = cos(gamma);
  sg = sin(gamma);
  R_11 = cb*cg;
  R_12 = -cb*sg;
  R_13 = sb;
  R_21 = sa*sb*cg + ca*sg;
  R_22 = -sa*sb*sg + ca*cg;
  R_23 = -sa*cb;
  R_31 = -ca*sb*cg + sa*sg;
  R_32 = ca*sb*sg + sa*cg;
  R_33 = ca*cb;
  // omega = G*der(theta), G = [cb*cg, sg, 0; -cb*sg, cg, 0; sb, 0, 1]
  om_x = cb*cg*w_alpha + sg*w_beta;
  om_y = -cb*sg*w_alpha + cg*w_beta;
  om_z = sb*w_alpha + w_gamma;
  gd_x = (-sb*cg*w_beta - cb*sg*w_gamma)*w_alpha + cg*w_gamma*w_beta;
  gd_y = (sb*sg*w_beta - cb*cg*w_gamma)*w_alpha - sg*w_gamma*w_beta;
  gd_z = cb*w_beta*w_alpha;
  // omega_d = G*der(w) + gd, solved for der(w) with inverse(G) = [cg/cb, -sg/cb, 0; sg, cg, 0;
  // -sb*cg/cb, sb*sg/cb, 1] (det G = cos(beta))
  der(w_alpha) = (cg*(omd_x - gd_x) - sg*(omd_y - gd_y))/cb;
  der(w_beta) = sg*(omd_x - gd_x) + cg*(omd_y - gd_y);
  der(w_gamma) = (-sb*cg*(omd_x - gd_x) + sb*sg*(omd_y - gd_y))/cb + omd_z - gd_z;

  // Matrix force element (eq. 1): element outputs with eq. 1's sign
  F_x = c_x*x + d_x*v_x;
  F_y = F_spring_y + d_y*v_y + F_fric + (if ve_k > 0 then F_ve else 0)
    "total axial force: eq. 1 plus the effects of MODEL.md";
  F_z = c_z*z + d_z*v_z;
  T_alpha = c_alpha*alpha + d_alpha*w_alpha;
  T_beta = c_beta*beta + d_beta*w_beta;
  T_gamma = c_gamma*gamma + d_gamma*w_gamma;
  // ... acting on the screw: the force F_I = -{F_x, F_y, F_z} at P, and the rotational part as
  // generalised forces Q_I = -{T_alpha, T_beta, T_gamma} on the angles: the body torque tau_I with
  // transpose(G)*tau_I = Q_I
  tau_x = -(cg*T_alpha + sg*cb*T_beta - sb*cg*T_gamma)/cb;
  tau_y = -(-sg*T_alpha + cg*cb*T_beta + sb*sg*T_gamma)/cb;
  tau_z = -T_gamma;

  // Effects beyond eq. 1 (fmu/MODEL.md): the axial spring force F_s and the states of the effects.
  // Backlash gap: the spring sees the elastic displacement y_e (softplus-rounded corners at +-gap).
  y_e = if gap > 0 then ScrewVertebraSoftplus(y - gap, smooth_w) - ScrewVertebraSoftplus(-y - gap, smooth_w) else y;
  v_e = if gap > 0 then (ScrewVertebraSoftplusSlope(y - gap, smooth_w) + ScrewVertebraSoftplusSlope(-y - gap, smooth_w))*v_y else v_y;
  // Force-displacement table: piecewise linear through the first tab_n points, linear beyond its ends,
  // written as the first segment's line plus a ramp at every inner point
  F_tab = tab_F[1] + tab_s1*(y_e - tab_y[1])
    + (if tab_n > 2 then (tab_s2 - tab_s1)*max(y_e - tab_y[2], 0) else 0)
    + (if tab_n > 3 then (tab_s3 - tab_s2)*max(y_e - tab_y[3], 0) else 0)
    + (if tab_n > 4 then (tab_s4 - tab_s3)*max(y_e - tab_y[4], 0) else 0)
    + (if tab_n > 5 then (tab_s5 - tab_s4)*max(y_e - tab_y[5], 0) else 0)
    + (if tab_n > 6 then (tab_s6 - tab_s5)*max(y_e - tab_y[6], 0) else 0)
    + (if tab_n > 7 then (tab_s7 - tab_s6)*max(y_e - tab_y[7], 0) else 0)
    + (if tab_n > 8 then (tab_s8 - tab_s7)*max(y_e - tab_y[8], 0) else 0)
    + (if tab_n > 9 then (tab_s9 - tab_s8)*max(y_e - tab_y[9], 0) else 0)
    + (if tab_n > 10 then (tab_s10 - tab_s9)*max(y_e - tab_y[10], 0) else 0)
    + (if tab_n > 11 then (tab_s11 - tab_s10)*max(y_e - tab_y[11], 0) else 0)
    + (if tab_n > 12 then (tab_s12 - tab_s11)*max(y_e - tab_y[12], 0) else 0)
    + (if tab_n > 13 then (tab_s13 - tab_s12)*max(y_e - tab_y[13], 0) else 0)
    + (if tab_n > 14 then (tab_s14 - tab_s13)*max(y_e - tab_y[14], 0) else 0)
    + (if tab_n > 15 then (tab_s15 - tab_s14)*max(y_e - tab_y[15], 0) else 0);
  // Spring: yield softening replaces c_y*y_e (or the table force) by yield_ratio*F_el +
  // (1 - yield_ratio)*yield_F*z_y; bilinear stiffness adds (nl_ratio - 1)*c_y past the breakpoint.
  F_el = if tab_n >= 2 then F_tab else c_y*y_e;
  F_spring_u = (if yield_on then yield_ratio*F_el + (1 - yield_ratio)*yield_F*z_y else F_el)
    + (if nl_ratio < 1 or nl_ratio > 1 then (nl_ratio - 1)*c_y*(ScrewVertebraSoftplus(y_e - nl_y_b, smooth_w)
       - ScrewVertebraSoftplus(-y_e - nl_y_b, smooth_w)) else 0);
  // Bouc-Wen, n = 4: the rate is continuous in (z, v), so the switch H(z*v) needs no event
  der(z_y) = if yield_on then
      smooth(0, v_e/y_Y*(1 - (if noEvent(z_y*v_e > 0) then z_y^4 else 0)))
    else 0;
  der(z_f) = if fric_F > 0 then
      smooth(0, v_y/fric_x*(1 - (if noEvent(z_f*v_y > 0) then z_f^4 else 0)))
    else 0;
  F_fric = if fric_F > 0 then fric_F*z_f else 0;
  // Interface damage: kappa follows the largest |y_e| reached; the spring softens to the residual force
  der(kappa) = if dmg_rate > 0 then
      smooth(0, (if noEvent(y_e*v_e > 0) then abs(v_e) else 0)*ScrewVertebraSoftplusSlope(abs(y_e) - kappa, smooth_w))
    else 0;
  past = ScrewVertebraSoftplus(kappa - dmg_y0, smooth_w);
  dmg_D = if dmg_rate > 0 then 1 - exp(-dmg_rate*past) else 0;
  F_spring_y = if dmg_rate > 0 then (1 - dmg_D)*F_spring_u + dmg_D*dmg_F_res*y_e/(dmg_y0 + past) else F_spring_u;
  // Maxwell branch: spring ve_k in series with a dashpot ve_k*ve_tau (its force stays 0 while ve_k = 0)
  der(F_ve) = if ve_k > 0 then ve_k*v_y - F_ve/ve_tau else 0;
  // Sensor offsets: biases of the measuring channels
  F_meas = F_pull + F_offset;
  y_meas = y + y_offset;

  // Load case
  F_load = if time < 0 then 0
           elseif unload and time >= t_unload then
             (if time >= t_unload + t_ramp then 0 else F_max*(1 - (time - t_unload)/t_ramp))
           elseif time < t_ramp then F_max*time/t_ramp
           else F_max;
  if mode == 2 then
    y = if use_y_in then y_in else v_pull*time "y prescribed; F_pull is the reaction of the drive";
  else
    F_pull = F_load;
  end if;
  F_H_x = F_ext_x;
  F_H_y = F_pull + F_ext_y;
  F_H_z = F_ext_z;

  // Newton-Euler equations about the centre of gravity. Translation, in V:
  // m*(der(v) + R*e) = F_I + F_H with e = omega_d x b + omega x (omega x b)
  wb_x = om_y*b_z - om_z*b_y;
  wb_y = om_z*b_x - om_x*b_z;
  wb_z = om_x*b_y - om_y*b_x;
  e_x = omd_y*b_z - omd_z*b_y + om_y*wb_z - om_z*wb_y;
  e_y = omd_z*b_x - omd_x*b_z + om_z*wb_x - om_x*wb_z;
  e_z = omd_x*b_y - omd_y*b_x + om_x*wb_y - om_y*wb_x;
  m*(der(v_x) + R_11*e_x + R_12*e_y + R_13*e_z) = -F_x + F_H_x;
  m*(der(v_y) + R_21*e_x + R_22*e_y + R_23*e_z) = -F_y + F_H_y;
  m*(der(v_z) + R_31*e_x + R_32*e_y + R_33*e_z) = -F_z + F_H_z;
  // Rotation, in S: I_B*omega_d + omega x (I_B*omega) = (-b) x (transpose(R)*F_I) + h x (transpose(R)*F_H)
  // + tau_I + transpose(R)*T_ext
  F_Ib_x = -(R_11*F_x + R_21*F_y + R_31*F_z);
  F_Ib_y = -(R_12*F_x + R_22*F_y + R_32*F_z);
  F_Ib_z = -(R_13*F_x + R_23*F_y + R_33*F_z);
  F_Hb_x = R_11*F_H_x + R_21*F_H_y + R_31*F_H_z;
  F_Hb_y = R_12*F_H_x + R_22*F_H_y + R_32*F_H_z;
  F_Hb_z = R_13*F_H_x + R_23*F_H_y + R_33*F_H_z;
  Iom_x = I_xx*om_x + I_xy*om_y + I_xz*om_z;
  Iom_y = I_xy*om_x + I_yy*om_y + I_yz*om_z;
  Iom_z = I_xz*om_x + I_yz*om_y + I_zz*om_z;
  M_x = -(b_y*F_Ib_z - b_z*F_Ib_y) + h_y*F_Hb_z - h_z*F_Hb_y + tau_x
    + R_11*T_ext_x + R_21*T_ext_y + R_31*T_ext_z - (om_y*Iom_z - om_z*Iom_y);
  M_y = -(b_z*F_Ib_x - b_x*F_Ib_z) + h_z*F_Hb_x - h_x*F_Hb_z + tau_y
    + R_12*T_ext_x + R_22*T_ext_y + R_32*T_ext_z - (om_z*Iom_x - om_x*Iom_z);
  M_z = -(b_x*F_Ib_y - b_y*F_Ib_x) + h_x*F_Hb_y - h_y*F_Hb_x + tau_z
    + R_13*T_ext_x + R_23*T_ext_y + R_33*T_ext_z - (om_x*Iom_y - om_y*Iom_x);
  omd_x = J_xx*M_x + J_xy*M_y + J_xz*M_z;
  omd_y = J_xy*M_x + J_yy*M_y + J_yz*M_z;
  omd_z = J_xz*M_x + J_yz*M_y + J_zz*M_z;

  // Monitors (the FMU's solver computes them; fmu/codegen.py leaves these equations out). |y| has a
  // local maximum where y*v_y changes sign from + to -: the running maximum is the largest such value so
  // far or the current |y|, whichever is larger (likewise for |v_y|).
  when y*v_y < 0 then
    y_hold = max(pre(y_hold), abs(y));
  end when;
  y_max = max(y_hold, abs(y));
  when v_y*a_y < 0 then
    v_hold = max(pre(v_hold), abs(v_y));
  end when;
  v_y_max = max(v_hold, abs(v_y));
  at_rest = abs(v_y) <= eps_v_eq and abs(a_y) <= eps_a_eq;
  when {initial(), at_rest} then
    t_rest = time;
  end when;
  t_eq = if at_rest then t_rest else -1;
  der(y_int) = y;
  der(v_abs_int) = abs(v_y);
  y_mean = if time > 0 then y_int/time else y;
  v_y_mean = if time > 0 then v_abs_int/time else abs(v_y);

  // The FMU counts its internal solver steps; a Modelica tool has no such variable.
  n_steps = 0;

  annotation(experiment(StartTime=0, StopTime=12, Interval=0.01, Tolerance=1e-06));
end ScrewVertebra;
