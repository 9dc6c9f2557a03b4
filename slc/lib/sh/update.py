r"""The SH cache update, shared by the ``sh`` method and the adaptive cache's SH records:
light samples at an entry's point projected onto an encoding's basis, and the running
mean of the coefficients.

One cycle draws :math:`n` (``rays``) light samples at the entry's point x
(:func:`slc.scene.lights.sample_light` and a shadow ray; lights below the surface's geometric
normal are dropped) and estimates, in the frame the caller gives (the world's for ``sh``,
the entry's own for the adaptive pool),

.. math:: \hat\lambda_{lm} = \frac1n \sum_k \frac{L_e(\omega_k) V_k}{p(\omega_k)} Y_{lm}(\omega_k).

The running mean counts samples, as the cones' C does:

.. math:: C \leftarrow \min(C + n, C_{max}), \qquad
          \lambda \leftarrow \lambda + \min(n / C, 1)\,(\hat\lambda - \lambda),

so a cycle of n samples weighs n / C (a 1-sample cycle weighs an eighth of an 8-sample
one), and once C reaches :math:`C_{max}` (``max_count``, in samples) the mean is an
exponential moving average, so that moving lights fade in.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from slc.scene.lights import sample_light, visible
from slc.lib.sh.project import project


def world_frame() -> mi.Frame3f:
    """The world's frame (directions in world coordinates)."""
    return mi.Frame3f(mi.Vector3f(1.0, 0.0, 0.0), mi.Vector3f(0.0, 1.0, 0.0), mi.Vector3f(0.0, 0.0, 1.0))


@dataclass
class ProjectionLoop:
    """The sample loop's state (one lane per entry): ``i`` the samples drawn, ``acc`` the
    sums of their projections (one array per coefficient), ``rng`` the random numbers,
    ``extra`` the observer's state."""
    i: mi.UInt32
    acc: list
    rng: mi.PCG32
    extra: object


def project_samples(scene: mi.Scene, si: mi.SurfaceInteraction3f, frame: mi.Frame3f, rays: mi.UInt32,
                    rng: mi.PCG32, valid: mi.Bool, enc, observer=None, two=None):
    """The sums over ``rays`` light samples per entry (points ``si``, lanes ``valid``) of
    their projections onto ``enc``'s basis, directions in ``frame``: (list of ``enc.n``
    arrays, the observer's state). ``observer`` (a
    :class:`slc.lib.cones.cycle.SampleObserver`, optional) sees every sample with its
    direction in ``frame``. Light below the surface's horizon is dropped, except on the
    ``two`` lanes (entries on two-sided BSDFs, :func:`slc.scene.bsdf_table.two_sided`; None:
    none), whose pixels on the back see it. The horizon is the geometric normal's, turned to
    the shading normal's side (a mirroring transform reverses a mesh's winding, so its
    geometric normal, and not its shading normal, points into the object)."""
    N = dr.width(valid)
    ng = mi.Vector3f(si.n)
    ng = dr.mulsign(ng, dr.dot(ng, si.sh_frame.n))
    valid = mi.Bool(valid)

    def cond(st: ProjectionLoop):
        return st.i < rays

    def body(st: ProjectionLoop):
        u = mi.Point2f(st.rng.next_float32(), st.rng.next_float32())
        ds, w, ok = sample_light(scene, si, u, valid & (st.i < rays))
        above = dr.dot(ds.d, ng) > 0.0
        ok &= (above if two is None else above | two) & dr.all(dr.isfinite(w))
        ok = visible(scene, si, ds, ok)
        s = frame.to_local(ds.d)
        if observer is not None:
            st.extra = observer.observe(st.extra, ds, w, ok, s)
        st.acc = [a + b for a, b in zip(st.acc, project(enc, s, dr.select(ok, w, 0.0)))]
        st.i = st.i + 1
        return (st,)

    z = dr.zeros(mi.Float, N)
    extra = observer.init(N) if observer is not None else ()
    st, = dr.while_loop(state=(ProjectionLoop(mi.UInt32(0), [mi.Float(z) for _ in range(enc.n)], rng, extra),),
                        cond=cond, body=body, labels=("projection",))
    return st.acc, st.extra


def running_mean(old: list, C: mi.Float, acc: list, rays: mi.UInt32, max_count: float):
    """The coefficients ``old`` (count ``C``, in samples) updated with a cycle's sums
    ``acc`` of ``rays`` samples (see the module): (new coefficients, new count). A cycle
    without samples counts as one (its sums are 0)."""
    n_s = mi.Float(dr.maximum(mi.UInt32(rays), 1))
    inv = dr.rcp(n_s)
    C = dr.minimum(C + n_s, float(max_count))
    a = dr.minimum(n_s * dr.rcp(C), 1.0)
    return [dr.fma(a, s * inv - o, o) for s, o in zip(acc, old)], C
