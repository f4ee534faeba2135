"""The solve's plan: which sub-solves run, in what order, with which rules (the ``solve`` stage's domain).

Entry point: :func:`objcam.solvers.plan.capture.solve_capture` (targets in, :class:`TargetSolution` per target
out; the stage loads and writes). Reading order:

- :mod:`~objcam.solvers.plan.params` (``SolveParams``: every setting) and :mod:`~objcam.solvers.plan.defaults`
  (the measured defaults, each with how it was chosen);
- :mod:`~objcam.solvers.plan.capture`: the capture split into independent problems, each sent to its plan;
- :mod:`~objcam.solvers.plan.known`: known albedo, each target alone (weights, edge or quadratic solve,
  supersampled A, chroma split);
- :mod:`~objcam.solvers.plan.unknown`: unknown albedo, the joint problem: camera blocks, joint setup,
  :mod:`~objcam.solvers.plan.bounce` (the joint solve and its bounce refits), :mod:`~objcam.solvers.plan.final`
  (the albedo's TV step and the envmaps at it), the per-target results;
- :mod:`~objcam.solvers.plan.rules`: the rules that choose weights and bases;
- :mod:`~objcam.solvers.plan.summary`: the stage's summary line and its warnings.

The numerical solvers the plan calls live beside it in objcam.solvers (nnls, edges, chroma, basis, refine, joint,
jointauto, albedo_tv, adam).
"""
