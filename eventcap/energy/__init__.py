"""The energy terms the solves compose (core library; plugins import it, never each other).

Each piece is a named term of the pose energy, evaluated either as a CasADi expression (small per-frame terms,
differentiated by CasADi) or in numpy with exact derivatives (terms over thousands of surface points):

- :mod:`.kernels` — closed-form camera projection derivatives; per-frame skinning transforms G(S) with their
  Jacobian and contracted second derivatives (posed point = WX · G).
- :mod:`.detections` — E_2D (optionally Cauchy-robust) and E_3D of one frame, the one-frame fit to them and its
  closed-form start; the per-frame detections container.
- :mod:`.correspondences` — the event correspondences of E_cor (ICP-style search by rasterising the current
  estimate) and the indicator φ of E_temp.
- :mod:`.cor` — E_cor and E_temp over consecutive frames (value, gradient, exact block-tridiagonal Hessian).
- :mod:`.spline` — cubic B-splines in the 33 pose parameters: basis matrices and the exact acceleration / jerk
  integral (the motion prior of the spline solve).
- :mod:`.silence` — the event-silence term's measurement: which joints made no more events than the background,
  per time bin (a joint without events is at rest; not in the paper).
- :mod:`.sil` — E_sil (paper Sec. 3.3): the posed template's silhouette boundary (:mod:`.boundary`) against its
  closest events (:mod:`.event_search`), point-to-line, value, gradient and exact block-diagonal Hessian (the
  refinement stage's energy, and a term of the spline solve); compiled loops in :mod:`._sil_kernels`.
- :mod:`.ipopt` — pinned IPOPT options, status checks, numpy callbacks, pose bounds.

Submodules import CasADi; nothing here is imported by ``import eventcap``.
"""
