// InterfaceElement: a one-degree-of-freedom interface force element, the spring-damper of eq. 1 (Kramer and
// Bauer) with the effects beyond eq. 1 of fmu/MODEL.md, for coupling to a multibody model that cannot be edited
// (co-simulation: the model gives the interface's relative displacement s and its rate v, the element gives
// back the force F it carries).
//
// Usable for translation (s in m, v in m/s, F in N, c in N/m, d in N.s/m) and for rotation (s in rad, v in
// rad/s, F in N.m, c in N.m/rad, d in N.m.s/rad): the variables carry no unit for that reason; the
// parameters that are lengths in translation (gap, nl_y_b, fric_x, dmg_y0, smooth_w, y_offset) are angles
// in rotation.
//
// The effects are those of ScrewVertebra's axial interface force (modelica/ScrewVertebra.mo), with the same
// parameter names and the same formulations, s in the place of y, c of c_y, d of d_y, so that a model split
// at the interface and coupled with this element reproduces ScrewVertebra with the effect inside. With
// w = smooth_w, S(u) = w*log(1 + exp(u/w)) and sigma(u) = dS/du:
//  - backlash gap: elastic displacement s_e = S(s - gap) - S(-s - gap) (s_e = s when gap = 0);
//  - spring F_s = yield_ratio*c*s_e + (1 - yield_ratio)*yield_F*z_y + (nl_ratio - 1)*c*(S(s_e - nl_y_b)
//    - S(-s_e - nl_y_b));
//  - Bouc-Wen states (n = 4, 0 at the start): der(z_y) = (v_e/s_Y)*(1 - H(z_y*v_e)*z_y^4), s_Y = yield_F/c;
//    der(z_f) = (v/fric_x)*(1 - H(z_f*v)*z_f^4), F_fric = fric_F*z_f;
//  - Maxwell branch, 0 at the start: der(F_ve) = ve_k*v - F_ve/ve_tau;
//  - damage: der(kappa) = max(0, sign(s_e)*v_e)*sigma(|s_e| - kappa), D = 1 - exp(-dmg_rate*S(kappa - dmg_y0)),
//    spring (1 - D)*F_s + D*dmg_F_res*s_e/(dmg_y0 + S(kappa - dmg_y0));
//  - F = F_s + d*v + F_fric + F_ve (positive F resists positive s); measured F_meas = F + F_offset,
//    s_meas = s + y_offset.
// Every effect is off at its parameters' defaults: F = c*s + d*v.
//
// Written in the subset of Modelica that fmu/codegen.py translates into C (see ScrewVertebra.mo). The states
// z_y, z_f, F_ve, kappa are public outputs: the FMU's continuous states (model exchange) and its history.

function InterfaceElementSoftplus
  "S(u) = w*log(1 + exp(u/w)): max(u, 0) with the corner rounded over w (written so that exp cannot overflow)"
  input Real u;
  input Real w "Rounding width, > 0";
  output Real S;
algorithm
  S := max(u, 0) + w*log(1 + exp(-abs(u)/w));
  annotation(smoothOrder=1);
end InterfaceElementSoftplus;

function InterfaceElementSoftplusSlope
  "sigma(u) = dS/du = 1/(1 + exp(-u/w)) of InterfaceElementSoftplus (written so that exp cannot overflow)"
  input Real u;
  input Real w "Rounding width, > 0";
  output Real sigma;
algorithm
  sigma := exp(-max(-u, 0)/w)/(1 + exp(-abs(u)/w));
  annotation(smoothOrder=1);
end InterfaceElementSoftplusSlope;

model InterfaceElement
  "One-DOF interface force element: spring-damper (eq. 1) with gap, bilinear stiffness, yield, friction, Maxwell branch, damage and sensor offsets, for translation or rotation"

  // Spring-damper (eq. 1)
  parameter Real c = 823224 "Stiffness (N/m in translation, N.m/rad in rotation)";
  parameter Real d = 488 "Damping (N.s/m in translation, N.m.s/rad in rotation)";

  // Effects beyond eq. 1 (fmu/MODEL.md): the defaults switch them off
  parameter Real gap = 0 "Backlash: slack, no spring force while |s| < gap (0: off)";
  parameter Real nl_ratio(unit="1") = 1 "Nonlinear stiffness: stiffness past the breakpoint divided by c (1: off)";
  parameter Real nl_y_b = 0.0005 "Nonlinear stiffness: breakpoint displacement";
  parameter Real yield_ratio(unit="1") = 1 "Yield: post-yield stiffness divided by c (1: off)";
  parameter Real yield_F = 100 "Yield: force (torque) at which the interface yields";
  parameter Real fric_F = 0 "Coulomb friction: sliding force (torque) opposing the motion (0: off)";
  parameter Real fric_x = 1e-05 "Coulomb friction: pre-sliding displacement";
  parameter Real ve_k = 0 "Viscoelastic relaxation: stiffness of the Maxwell branch (0: off)";
  parameter Real ve_tau(unit="s") = 1 "Viscoelastic relaxation: relaxation time of the Maxwell branch";
  parameter Real F_offset = 0 "Sensor offset: bias added to the measured force F_meas";
  parameter Real y_offset = 0 "Sensor offset: bias added to the measured displacement s_meas";
  parameter Real smooth_w = 1e-06 "Width over which the corners of the gap and the breakpoint are rounded";
  parameter Real dmg_rate = 0 "Interface damage: softening rate per unit of displacement past the onset, D = 1 - exp(-dmg_rate*(kappa - dmg_y0)) (0: off)";
  parameter Real dmg_y0 = 0.0005 "Interface damage: onset displacement (the largest |s| reached before damage starts)";
  parameter Real dmg_F_res = 0 "Interface damage: residual force of the fully damaged interface (friction plateau)";

  // Solver setting of the co-simulation interface: a Modelica tool ignores it
  parameter Real rtol = 1e-06 "Relative local error tolerance of the co-simulation interface's integrator of the states";

  // Inputs: the interface's motion
  input Real s(start=0) "Relative displacement (m) or angle (rad) of the interface";
  input Real v(start=0) "Rate of s (m/s or rad/s)";

  // Outputs
  output Real F "Force (N) or torque (N.m) the element carries, positive resisting positive s";
  output Real F_meas "Measured force: F + F_offset";
  output Real s_meas "Measured displacement: s + y_offset";
  output Real F_fric "Friction part of F";
  output Real dmg_D(unit="1") "Interface damage: the damage variable D (0 undamaged, towards 1 failed)";
  // Outputs that are the element's states (0 at the start)
  output Real z_y(unit="1", start=0) "Bouc-Wen yield state";
  output Real z_f(unit="1", start=0) "Bouc-Wen friction state";
  output Real F_ve(start=0) "Maxwell branch part of F";
  output Real kappa(start=0) "Largest elastic displacement |s_e| reached (interface damage)";

protected
  final parameter Real s_Y = yield_F/c "Yield displacement of the Bouc-Wen yield state";
  final parameter Boolean yield_on = yield_ratio < 1 or yield_ratio > 1 "Yield softening switched on";
  Real s_e "Elastic displacement after the backlash gap";
  Real v_e "Rate of s_e";
  Real F_el "Elastic force c*s_e";
  Real F_spring_u "Spring force before damage";
  Real F_spring "Spring force";
  Real past "Displacement reached past the onset of damage, softplus(kappa - dmg_y0)";

initial equation
  z_y = 0;
  z_f = 0;
  F_ve = 0;
  kappa = 0;

equation
  assert(c >= 0 and d >= 0, "c and d must be >= 0");
  s_e = if gap > 0 then InterfaceElementSoftplus(s - gap, smooth_w) - InterfaceElementSoftplus(-s - gap, smooth_w) else s;
  v_e = if gap > 0 then (InterfaceElementSoftplusSlope(s - gap, smooth_w) + InterfaceElementSoftplusSlope(-s - gap, smooth_w))*v else v;
  F_el = c*s_e;
  F_spring_u = (if yield_on then yield_ratio*F_el + (1 - yield_ratio)*yield_F*z_y else F_el)
    + (if nl_ratio < 1 or nl_ratio > 1 then (nl_ratio - 1)*c*(InterfaceElementSoftplus(s_e - nl_y_b, smooth_w)
       - InterfaceElementSoftplus(-s_e - nl_y_b, smooth_w)) else 0);
  der(z_y) = if yield_on then
      smooth(0, v_e/s_Y*(1 - (if noEvent(z_y*v_e > 0) then z_y^4 else 0)))
    else 0;
  der(z_f) = if fric_F > 0 then
      smooth(0, v/fric_x*(1 - (if noEvent(z_f*v > 0) then z_f^4 else 0)))
    else 0;
  F_fric = if fric_F > 0 then fric_F*z_f else 0;
  der(kappa) = if dmg_rate > 0 then
      smooth(0, (if noEvent(s_e*v_e > 0) then abs(v_e) else 0)*InterfaceElementSoftplusSlope(abs(s_e) - kappa, smooth_w))
    else 0;
  past = InterfaceElementSoftplus(kappa - dmg_y0, smooth_w);
  dmg_D = if dmg_rate > 0 then 1 - exp(-dmg_rate*past) else 0;
  F_spring = if dmg_rate > 0 then (1 - dmg_D)*F_spring_u + dmg_D*dmg_F_res*s_e/(dmg_y0 + past) else F_spring_u;
  der(F_ve) = if ve_k > 0 then ve_k*v - F_ve/ve_tau else 0;
  F = F_spring + d*v + F_fric + (if ve_k > 0 then F_ve else 0);
  F_meas = F + F_offset;
  s_meas = s + y_offset;

  annotation(experiment(StartTime=0, StopTime=1, Interval=0.001, Tolerance=1e-06));
end InterfaceElement;
