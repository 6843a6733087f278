"""A study whose runs take as long as one likes, for the tests of the time limits (test_faults, test_dask_cluster)."""

#: The 6-DOF load case with h_max = 1e-9 s: about 1e8 internal steps over 0.1 s (minutes of computing), next
#: to a fast run (h_max = 1e-5 s, ~0.1 s). max_steps is raised to nearly its Integer limit so that only the
#: time limit can stop the slow run.
SLOW = """\
name: slow
fmu: default
parameters:
  h: {variable: h_max, unit: s}
fixed: {F_max: 411, t_ramp: 0.05, max_steps: 2000000000}
scenario: {stop_time: 0.1, inputs: {F_ext_x: 20}}
metrics:
  max_y: {output: y_max, unit: m}
stages:
  grid: {values: {h: [1.0e-5, 1.0e-9]}}
execution: {workers: 1, timeout_s: 1}
"""
