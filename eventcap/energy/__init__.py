"""The energy terms the solves compose (core library; plugins import it, never each other).

Every term is a factor (:mod:`.factor`): one class with its settings (``terms.<name>.weight`` and more in a solve's
config) that collects its data from a window's inputs (:mod:`.window`), relinearises at each ICP round and gives its
value, gradient and Hessian blocks in pose space at its own sample times.
A solve is a list of factors built from its config (:func:`.terms.factors_from_config`) summed over a
parametrisation of the poses (:mod:`.problem`: a cubic B-spline's control points, or one pose per frame) and
handed to IPOPT. The terms (the table in :mod:`.terms`):

- :mod:`.detections` — E_2D (optionally Cauchy-robust) and E_3D of one frame as CasADi expressions, mapped over the
  detection frames; the one-frame fit to them (the paper's initialisation) with its closed-form start; the
  per-frame detections container.
- :mod:`.cor` — E_cor and E_temp over consecutive frames (numpy, exact block-tridiagonal Hessian); their data come
  from :mod:`.correspondences` (ICP-style search by rasterising the current estimate, and the indicator φ).
- :mod:`.sil` — E_sil (paper Sec. 3.3): the posed template's silhouette boundary (:mod:`.boundary`) against its
  closest events (:mod:`.event_search`), point-to-line; E_stab; compiled loops in :mod:`._sil_kernels`.
- :mod:`.silence` — E_still, the event-silence term (not in the paper), and its measurement: which joints made no
  more events than the background, per time bin.
- :mod:`.prior` — the motion prior and the context pull (not in the paper), and the choice of their data from the
  per-frame fits around a window.

And what they share: :mod:`.kernels` (closed-form projection derivatives; per-frame skinning transforms G(S) with
their Jacobian and contracted second derivatives), :mod:`.spline` (cubic B-splines in the pose parameters),
:mod:`.ipopt` (pinned IPOPT options, status checks, numpy callbacks, pose bounds), :mod:`.errors`.

Submodules import CasADi; nothing here is imported by ``import eventcap``.
"""
