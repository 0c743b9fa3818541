"""Implementation of the body stage: the person's body from the detections (eventcap/body/proportions.py)."""

from __future__ import annotations

import dataclasses

import numpy as np

from eventcap.body.proportions import (
    DETECTOR_DEFINITIONS,
    SEGMENTS,
    BodyEstimate,
    detector_spread,
    fit_body,
    floor_depths,
    foot_geometry,
    rest_spread,
    seen_segments,
)
from eventcap.worldframe import upright

#: The ANNY parameters a template may state (template.<name>); "shape": a whole body (a scan, a model file).
ANNY_PARAMS = ("height_m", "build", "muscle", "sex")


def detector_definitions(detector: str) -> tuple[dict, str]:
    """The detector's own segment definitions (:data:`DETECTOR_DEFINITIONS`) by the start of its name, and which."""
    for name, table in DETECTOR_DEFINITIONS.items():
        if detector.lower().startswith(name):
            return table, name
    return {}, ""


def run_proportions(inputs, config, ctx):
    from eventcap.body.anny import anny_phenotypes, anny_rest_joints, anny_template, is_anny

    rec, det, template = inputs["recording"], inputs["detections"], inputs["template"]
    stated = set(template.stated)

    def keep(why: str, est: BodyEstimate | None = None):
        """The template's body; when something of it is not stated, with the prior's spread (nothing was seen
        to narrow it)."""
        body = template
        if est is not None and est.uncertain:
            spread_joints = rest_spread(est, rest_joints)
            body = dataclasses.replace(template, rest_spread=spread_joints if spread_joints.shape[0] else None)
            why += ("; its uncertainty the prior's: " + ", ".join(
                f"{q} +- {est.sd(q):.3f}" + (" m" if q == "height_m" else "") for q in est.uncertain))
        ctx.log.info("body: the template as given (%s): %s", why, template.name)
        ctx.stats["body"] = {"estimated": [], "why": why, "uncertain": list(est.uncertain) if est else []}
        return {"recording": dataclasses.replace(rec, template=body), "template": body}

    if not config.estimate:
        return keep("stages.body.estimate=false")
    if "shape" in stated:
        return keep("a whole body was given")
    anny = is_anny(template)
    free = ([p for p in ("height_m", "sex", "muscle") if p not in stated] if anny
            else [] if "height_m" in stated else ["height_m"])
    if not free:
        return keep(f"it states {', '.join(sorted(stated))}"
                    + ("" if anny else "; proportions are estimated for ANNY templates only"))
    floor_known = rec.world == "" and config.scale_from_floor
    if anny:
        start = anny_phenotypes(template)
        rest_joints = anny_rest_joints
    else:
        h0 = float(np.ptp(template.vertices[:, 1]))
        start = {"height_m": h0, "build": 0.0, "muscle": 0.0, "sex": 0.0}

        def rest_joints(height_m, build, muscle, sex):
            return template.rest_joints * (height_m / h0)
    seen_rec = upright(rec, det)
    cam = seen_rec.camera
    args = (det.keypoints_2d, det.confidence_2d, det.joints_3d, det.confidence_3d)
    seen = seen_segments(cam, *args)
    feet = foot_geometry(template.rest_joints, template.rest_landmarks)
    floor_z = floor_depths(cam, *args, feet) if "height_m" in free and floor_known else None
    definitions, det_name = detector_definitions(det.detector)
    spread, spread_name = detector_spread(det.detector)
    camera_height = float(cam.center[1]) if floor_z is not None else None
    est = fit_body(seen, start, tuple(free), floor_z=floor_z, definitions=definitions, spread=spread,
                   rest_joints=rest_joints, camera_height_m=camera_height, stature_sd_m=config.stature_sd_m,
                   t_us=det.t_us)
    if "height_m" in free and "height_m" not in est.estimated and est.estimated:
        ctx.log.info("body: the stature stays the template's (%.3f m +- %.3f, the prior's): %s", start["height_m"],
                     est.sd("height_m"), est.scale_from)
    if not floor_known and "height_m" in free:
        ctx.log.info("body: the stature is the template's (%.3f m): without the floor and the camera's height (a "
                     "world from the camera's extrinsics) one camera cannot tell it; give template.height_m",
                     start["height_m"])
    if not est.estimated:
        return keep(est.why or f"nothing to estimate: {est.scale_from}", est)
    spread_joints = rest_spread(est, rest_joints)
    body = _body(template, est, anny, anny_template, spread_joints)
    _log(ctx, template, est, start, stated, det_name, det.detector, anny, spread_name)
    return {"recording": dataclasses.replace(rec, template=body), "template": body}


def _body(template, est: BodyEstimate, anny: bool, anny_template, spread_joints: np.ndarray):
    """The template with the estimated parameters and their uncertainty (``rest_spread``): an ANNY body in the
    template's outfit, or the template scaled uniformly about its feet (a template that is not ANNY's: its stature
    only)."""
    tag = ", ".join(f"{p} {getattr(est, p):+.3f}" if p != "height_m" else f"{est.height_m:.3f} m"
                    for p in est.estimated)
    spread = spread_joints if spread_joints.shape[0] else None
    if anny:
        b = anny_template(est.height_m, est.build, est.muscle, est.sex)
        return dataclasses.replace(b, name=f"{template.name} [estimated {tag}]",
                                   vertex_albedo=template.vertex_albedo, stated=template.stated, rest_spread=spread)
    k = est.height_m / float(np.ptp(template.vertices[:, 1]))
    return dataclasses.replace(template, name=f"{template.name} [estimated {tag}]", rest_joints=template.rest_joints * k,
                               vertices=template.vertices * k, landmark_offset=template.landmark_offset * k,
                               rest_spread=spread)


def _why_kept(m) -> str:
    """Why a quantity did not move (its evidence weighs little against the prior), or '' when it moved."""
    if m.seen is None:
        return "not seen across the line of sight in 3 images: it follows the rest of the body"
    if m.weight < 0.25:
        return f"its evidence weighs {100 * m.weight:.0f} % against the prior"
    return ""


def _log(ctx, template, est: BodyEstimate, start: dict, stated: set, det_name: str, detector: str, anny: bool,
         spread_name: str) -> None:
    st = est.stature
    if st is not None:
        delta = st.posterior - st.template
        ctx.log.info(
            "body: stature %.3f -> %.3f m +- %.3f (%+.1f cm; the prior +- %.3f; the floor and the camera's height "
            "alone: %.3f +- %.3f m from %d images, %.0f effective: the supporting foot's sole on the floor gives the "
            "person's depth): the evidence weighs %.0f %%%s", st.template, st.posterior, st.posterior_sd,
            100 * delta, st.prior_sd, st.seen, st.seen_se, st.images, st.effective, 100 * st.share,
            "" if abs(delta) >= 0.005 else "; it barely moved")
    for p in ("sex", "muscle"):
        if p in est.estimated:
            ctx.log.info("body: %s %+.3f -> %+.3f +- %.3f (ANNY's phenotype; the prior: the spread of human "
                         "proportions at the stature)", p, start[p], getattr(est, p), est.sd(p))
    used = {n: k for n, k in est.seen.items() if k >= 3}
    moved, kept = [], []
    for n in SEGMENTS:
        m = est.segments[n]
        text = (f"{n} {100 * m.template:.1f} -> {100 * m.posterior:.1f} +- {100 * m.posterior_sd:.1f}"
                + (f" [seen {100 * m.seen:.1f} +- {100 * m.seen_se:.1f} in {m.images} images; prior +- "
                   f"{100 * m.prior_sd:.1f}: weighs {100 * m.weight:.0f} %]" if m.seen is not None else ""))
        why = _why_kept(m)
        (kept if why or abs(m.posterior - m.template) < 0.002 else moved).append(text + (f" ({why})" if why else ""))
    ctx.log.info(
        "body: segment lengths (cm), template -> posterior +- SD, from %d segments seen across the line of sight in "
        "%d images (their noise %.2f x the model's, lag-1 correlation %.2f, %d of %d outliers)%s; moved: %s; "
        "kept: %s", len(used), est.images, est.noise.get("sigma", float("nan")), est.noise.get("rho", 0.0),
        est.noise.get("outliers", 0), est.noise.get("observations", 0),
        f"; the detector's definitions ({det_name}) removed" if det_name else
        f"; the detector ({detector.split(':')[0].split(' ')[0] or 'unnamed'}) taken to put its points on the joints",
        "; ".join(moved) or "none", "; ".join(kept) or "none")
    ctx.log.info("body: what the detector shares within a capture: %s, x%.2f for images spanning %.2f s; stated: %s%s",
                 f"the {spread_name} detector's" if spread_name else "an unknown detector's (the largest measured)",
                 est.noise.get("span_factor", 1.0), est.noise.get("span_s", 0.0),
                 ", ".join(sorted(stated)) if stated else "nothing",
                 "" if anny else " (not an ANNY template: its stature only)")
    ctx.stats["body"] = {
        "estimated": list(est.estimated), **{k: round(v, 4) for k, v in est.params().items()},
        "sd": {p: round(est.sd(p), 4) for p in est.uncertain}, "scale_from": est.scale_from, "images": est.images,
        "floor_images": est.floor_images, "seen": est.seen, "noise": {k: (round(v, 4) if isinstance(v, float) else v)
                                                                      for k, v in est.noise.items()},
        "stature": None if st is None else {"template": st.template, "posterior": round(st.posterior, 4),
                                            "sd": round(st.posterior_sd, 4), "floor": round(st.seen, 4),
                                            "floor_se": round(st.seen_se, 4), "share": round(st.share, 3)},
        "segments_cm": {n: {"posterior": round(100 * m.posterior, 2), "sd": round(100 * m.posterior_sd, 2),
                            "seen": None if m.seen is None else round(100 * m.seen, 2),
                            "seen_se": None if m.seen_se is None else round(100 * m.seen_se, 2),
                            "weight": round(m.weight, 3), "share": round(m.share, 3)}
                        for n, m in est.segments.items()}}
