"""The settings of the ``adaptive`` method (:class:`slc.methods.adaptive.method.AdaptiveCache`):
the lights listed in VISIBILITY records, the cone and SH representations, the ray policy, the
light statistics and the choice rule's thresholds, and the representation of new entries.
"""
from __future__ import annotations

from slc.methods import Param
from slc.lib.sh.ycocg import ENCODINGS
from slc.methods.cache_method import PayloadMethod

PARAMS = (
    Param("vis_lights", 12, "delta or small sphere lights with their own visibility per VISIBILITY entry", lo=1, hi=16),
    Param("sphere_lights", "small", "small sphere lights are listed in VISIBILITY records like delta lights "
          "(small: where r/d < sphere_sin; auto: so, in scenes whose every emitter is a delta or sphere "
          "light; off: never)", choices=("auto", "small", "off")),
    Param("sphere_sin", 0.3, "largest r/d (sine of the half-angle) of a sphere light listed at an entry",
          lo=0.0, hi=1.0),
    Param("vis_rays", 0.5, "share of the ray policy's update rays (at least one) traced by a VISIBILITY "
          "entry whose listed lights bring at least 95% of its light (its statistics' listed share), in a "
          "scene whose listable lights all fit a record (vis_lights): their unoccluded light is exact, only "
          "their visible fractions and the residual are estimated", lo=0.0, hi=1.0),
    Param("polygon_lights", "on", "rectangles and emitter meshes of at most 16 triangles (not spheres) are "
          "listed in VISIBILITY records at any size, their unoccluded irradiance exact at the pixel "
          "(Lambert's formula, clipped to the horizon) times the entry's visible fraction (on: so; "
          "off: never)", choices=("on", "off")),
    Param("polygon_glossy", "ltc", "a polygon light at a pixel whose glossy lobe is narrow against it (its peak "
          "density times the light's solid angle above 0.1). ltc: a GGX lobe's integral over the light by "
          "linearly transformed cosines (a fitted table; no ray, no sample) where the entry sees the light "
          "whole, the light as a point along its vector irradiance elsewhere; sample: polygon_samples pairs "
          "of light and BSDF samples of its term, the diffuse reflectance as a control variate, shadow rays "
          "where the entry sees part of the light; point: the light as a point along its vector irradiance",
          choices=("ltc", "sample", "point")),
    Param("polygon_samples", 16, "sample pairs (one from the light, one from the BSDF) per polygon light at a "
          "pixel sampled by polygon_glossy=sample", lo=1, hi=256),
    Param("env_lights", "auto", "bright small regions of the environment map are listed in VISIBILITY "
          "records as directional lights (auto: in scenes with an environment emitter whose map has such "
          "regions; off: never)", choices=("auto", "off")),
    Param("env_ratio", 10.0, "a pixel of the environment is bright above this multiple of the map's mean "
          "radiance", lo=1.0, hi=1e6),
    Param("env_max_sr", 0.05, "largest solid angle (sr) of a bright region listed as a light", lo=0.0, hi=12.6),
    Param("env_sky", "auto", "the rest of the environment map, the sky, is listed in VISIBILITY records with "
          "its SH irradiance (auto: where that irradiance is within 3% of the map's; off: never)",
          choices=("auto", "off")),
    Param("max_cones", 3, "cones per CONES entry", lo=1, hi=4),
    Param("encoding", "y3co1cg1", "SH encoding of SH entries", choices=tuple(ENCODINGS)),
    Param("sh_count", 128, "SH running-mean count cap (samples)", lo=1, hi=1e6),
    Param("shade_samples", 16, "cone shading directions per cone", lo=1, hi=1024),
    Param("glossy_samples", 8, "BSDF samples of the SH radiance per glossy pixel", lo=1, hi=1024),
    *PayloadMethod.ray_policy_params,
    Param("window", 32, "light statistics' running-mean window (updates)", lo=1, hi=63),
    Param("switch_after", 3, "updates in a row asking for another representation before a switch", lo=1, hi=63),
    Param("switch_period", 4, "switches are carried out in every k-th frame only (their conversion "
          "kernels are traced in those frames)", lo=1, hi=64),
    Param("switch_early", 4, "frames from the cache's start in which switches are carried out in every "
          "frame (young records hold little to lose; new entries start in the majority sooner)", lo=0, hi=64),
    Param("theta_delta", 0.5, "delta-light energy share above which VISIBILITY is chosen", lo=0.0, hi=1.0),
    Param("theta_glossy", 0.97, "theta_delta at glossy entries (their BSDF's glossy and delta lobes carry at "
          "least half of their light) whose other light is narrow (R >= theta_r): a VISIBILITY residual, light of "
          "unknown direction, is shaded as uniform radiance", lo=0.0, hi=1.0),
    Param("theta_r", 0.75, "mean resultant length below which SH is chosen", lo=0.0, hi=1.0),
    Param("sh_when", "never", "SH is a candidate of the choice only in scenes with an environment "
          "(infinite, non-delta) emitter, always, or never", choices=("environment", "always", "never")),
    Param("min_share", 0.02, "a representation fewer than this share of the active entries ask for "
          "is not used (its entries take the scene's prior; 0: no limit)", lo=0.0, hi=1.0),
    Param("start", "majority", "representation of new entries (majority: the one that held the most "
          "active entries at the last update, the scene's prior before; prior: from the scene's emitters)",
          choices=("majority", "prior", "visibility", "cones", "sh")),
    Param("force", "auto", "representation of every entry (auto: the choice rule)",
          choices=("auto", "visibility", "cones", "sh")),
    Param("freeze", True, "the representations' updates and shadings and the cache's entry interactions traced "
          "once and replayed (dr.freeze; the same images); off: traced every frame"),
)
