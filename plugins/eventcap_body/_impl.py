"""Implementation of the body stage: the person's body from the detections (eventcap/body/proportions.py)."""

from __future__ import annotations

import dataclasses

import numpy as np

from eventcap.body.proportions import (
    DETECTOR_DEFINITIONS,
    SEGMENTS,
    BodyEstimate,
    fit_body,
    floor_depths,
    seen_segments,
    segment_lengths,
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
    from eventcap.body.anny import anny_phenotypes, anny_template, is_anny

    rec, det, template = inputs["recording"], inputs["detections"], inputs["template"]
    stated = set(template.stated)

    def keep(why: str):
        ctx.log.info("body: the template as given (%s): %s", why, template.name)
        ctx.stats["body"] = {"estimated": [], "why": why}
        return {"recording": dataclasses.replace(rec, template=template), "template": template}

    if not config.estimate:
        return keep("stages.body.estimate=false")
    if "shape" in stated:
        return keep("a whole body was given")
    anny = is_anny(template)
    free = ([p for p in ("height_m", "sex", "muscle") if p not in stated] if anny
            else [] if "height_m" in stated else ["height_m"])
    floor_known = rec.world == "" and config.scale_from_floor
    if not floor_known and "height_m" in free:
        free.remove("height_m")
    if not free:
        return keep(f"it states {', '.join(sorted(stated)) or 'nothing'}"
                    + ("" if anny else "; proportions are estimated for ANNY templates only")
                    + ("" if floor_known or "height_m" in stated else
                       "; the stature needs the floor and the camera's height: a world from the camera's extrinsics"))
    seen_rec = upright(rec, det)
    cam = seen_rec.camera
    accepted = det.confidence_2d.max(axis=1) > 0
    if not accepted.any():
        return keep("no image with a detection")
    args = (det.keypoints_2d, det.confidence_2d, det.joints_3d, det.confidence_3d)
    seen = seen_segments(cam, *args)
    floor_z = floor_depths(cam, *args) if "height_m" in free else None
    definitions, det_name = detector_definitions(det.detector)
    if anny:
        start = anny_phenotypes(template)
        rest_joints = None
    else:
        h0 = float(np.ptp(template.vertices[:, 1]))
        start = {"height_m": h0, "build": 0.0, "muscle": 0.0, "sex": 0.0}

        def rest_joints(height_m, build, muscle, sex):
            return template.rest_joints * (height_m / h0)
    camera_height = float(cam.center[1]) if floor_z is not None else None
    est = fit_body(seen, start, tuple(free), floor_z=floor_z, definitions=definitions,
                   prior_sigma=config.prior_sigma, rest_joints=rest_joints, camera_height_m=camera_height)
    if "height_m" in free and "height_m" not in est.estimated:
        ctx.log.info("body: the stature stays the template's (%.3f m): %s", start["height_m"], est.scale_from)
    if not est.estimated:
        return keep(f"too few segments seen across the line of sight (each needs 3 images): "
                    f"{_counts(est)}")
    body = _body(template, est, anny, anny_template)
    _log(ctx, template, est, stated, floor_known, det_name, det.detector, anny)
    return {"recording": dataclasses.replace(rec, template=body), "template": body}


def _body(template, est: BodyEstimate, anny: bool, anny_template):
    """The template with the estimated parameters: an ANNY body in the template's outfit, or the template scaled
    uniformly about its feet (a template that is not ANNY's: its stature only)."""
    tag = ", ".join(f"{p} {getattr(est, p):+.3f}" if p != "height_m" else f"{est.height_m:.3f} m"
                    for p in est.estimated)
    if anny:
        b = anny_template(est.height_m, est.build, est.muscle, est.sex)
        return dataclasses.replace(b, name=f"{template.name} [estimated {tag}]",
                                   vertex_albedo=template.vertex_albedo, stated=template.stated)
    k = est.height_m / float(np.ptp(template.vertices[:, 1]))
    return dataclasses.replace(template, name=f"{template.name} [estimated {tag}]", rest_joints=template.rest_joints * k,
                               vertices=template.vertices * k, landmark_offset=template.landmark_offset * k)


def _counts(est: BodyEstimate) -> str:
    return ", ".join(f"{n} {k}" for n, k in est.seen.items())


def _log(ctx, template, est: BodyEstimate, stated: set, floor_known: bool, det_name: str, detector: str,
         anny: bool) -> None:
    before = segment_lengths(template.rest_joints)
    used = {n: k for n, k in est.seen.items() if k >= 3}
    what = []
    if "height_m" in est.estimated:
        what.append(f"stature {est.height_m:.3f} m (the template's {float(np.ptp(template.vertices[:, 1])):.3f}) "
                    f"from the floor and the camera's height ({est.floor_images} images: the supporting foot's sole "
                    "on the floor gives the person's depth)")
    for p in ("sex", "muscle"):
        if p in est.estimated:
            what.append(f"{p} {getattr(est, p):+.3f}")
    ctx.log.info(
        "body: estimated %s, from %d segments seen across the line of sight in %d images (%s)%s; kept: %s%s",
        "; ".join(what), len(used), est.images, ", ".join(f"{n} {k}" for n, k in used.items()),
        f"; the detector's definitions ({det_name}) removed" if det_name else
        f"; the detector ({detector.split(':')[0].split(' ')[0] or 'unnamed'}) taken to put its points on the joints",
        ", ".join(sorted(stated)) if stated else "nothing stated",
        "" if anny else " (not an ANNY template: its stature only)")
    body = segment_lengths(_rest(est, template, anny))
    ctx.log.info("body: segment lengths (cm), template -> estimated [seen]: %s",
                 ", ".join(f"{n} {100 * before[n]:.1f} -> {100 * body[n]:.1f}"
                           + (f" [{100 * est.measured_m[n]:.1f}]" if n in est.measured_m else "") for n in SEGMENTS))
    if not floor_known and "height_m" not in stated:
        ctx.log.info("body: the stature is the template's (%.3f m): without the floor and the camera's height (a "
                     "world from the camera's extrinsics) one camera cannot tell it; give template.height_m",
                     float(np.ptp(template.vertices[:, 1])))
    ctx.stats["body"] = {"estimated": list(est.estimated), **{k: round(v, 4) for k, v in est.params().items()},
                         "scale_from": est.scale_from, "images": est.images, "floor_images": est.floor_images,
                         "seen": est.seen}


def _rest(est: BodyEstimate, template, anny: bool) -> np.ndarray:
    if anny:
        from eventcap.body.anny import anny_rest_joints

        return anny_rest_joints(est.height_m, est.build, est.muscle, est.sex)
    return template.rest_joints * (est.height_m / float(np.ptp(template.vertices[:, 1])))
