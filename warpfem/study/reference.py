"""Independent reference solutions for the clamped cantilever under gravity: NGSolve and Euler-Bernoulli.

The beam occupies ``[0, L] x [0, h] x [0, w]`` (x along the beam, gravity along -y), clamped (all
displacement components zero) on the face x = 0. The reported value is the *sag*: the downward
displacement of the free end, averaged over the tip face x = L (m, positive downwards).

NGSolve solves the same beam with high-order H1 elements on a Netgen mesh, raising the polynomial order
until the sag stops changing (:func:`converged_sag`), either as linear elasticity or geometrically
nonlinear (Saint Venant-Kirchhoff, Newton with load stepping). :func:`sag_on_tets` solves on a given
tet mesh with P1 elements, so a warpfem run can be compared with linear and nonlinear FEM on exactly the
same discretisation (the same locking).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from warpfem.errors import InputError
from warpfem.sim.model import lame


@dataclass(frozen=True)
class Cantilever:
    """A clamped rectangular cantilever loaded by its own weight.

    Attributes:
        length: L, along x (m).
        height: h, along y, the bending direction (m).
        width: w, along z (m).
        young: Young's modulus E (Pa).
        poisson: Poisson's ratio.
        density: Density (kg/m^3).
        gravity: Gravitational acceleration, acting along -y (m/s^2).
    """

    length: float = 1.0
    height: float = 0.1
    width: float = 0.1
    young: float = 1.0e7
    poisson: float = 0.3
    density: float = 1000.0
    gravity: float = 9.81

    def __post_init__(self) -> None:
        for name in ("length", "height", "width", "young", "density", "gravity"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise InputError(f"cantilever {name} must be a positive finite number, got {value}")
        if not 0.0 <= self.poisson < 0.5:
            raise InputError(f"cantilever poisson must be in [0, 0.5), got {self.poisson}")

    def euler_bernoulli_sag(self) -> float:
        """Tip deflection of a slender beam under its own weight, w L^4 / (8 E I) (m)."""
        load = self.density * self.gravity * self.height * self.width  # N/m
        inertia = self.width * self.height**3 / 12.0
        return load * self.length**4 / (8.0 * self.young * inertia)


@dataclass(frozen=True)
class ConvergedSag:
    """The sag of a p-refinement study.

    Attributes:
        sag: Sag at the highest order solved (m).
        orders: The polynomial orders solved.
        sags: The sag at each order (m).
    """

    sag: float
    orders: tuple[int, ...]
    sags: tuple[float, ...]

    @property
    def change(self) -> float:
        """Relative change of the sag between the last two orders."""
        return abs(self.sags[-1] - self.sags[-2]) / abs(self.sags[-1])


def _solve(mesh, beam: Cantilever, order: int, nonlinear: bool, load_steps: int) -> float:
    """Solve the cantilever on an NGSolve mesh with boundaries 'clamp' and 'tip'; return the tip sag (m)."""
    import ngsolve as ng
    from ngsolve.solvers import Newton

    mu, lam = lame(beam.young, beam.poisson)
    fes = ng.VectorH1(mesh, order=order, dirichlet="clamp")
    u, v = fes.TnT()
    gfu = ng.GridFunction(fes)
    weight = beam.density * beam.gravity  # N/m^3, along -y
    ident = ng.Id(3)
    if nonlinear:
        factor = ng.Parameter(0.0)
        F = ident + ng.Grad(u)
        E = 0.5 * (F.trans * F - ident)
        energy = mu * ng.InnerProduct(E, E) + 0.5 * lam * ng.Trace(E) ** 2 + factor * weight * u[1]
        a = ng.BilinearForm(fes, symmetric=True)
        a += ng.Variation(energy.Compile() * ng.dx)
        for step in range(1, load_steps + 1):
            factor.Set(step / load_steps)
            converged, _ = Newton(a, gfu, maxit=50, maxerr=1e-11, inverse="sparsecholesky", printing=False)
            if converged < 0:
                raise RuntimeError(f"NGSolve Newton did not converge at load step {step}/{load_steps}")
    else:
        eps = ng.Sym(ng.Grad(u))
        a = ng.BilinearForm(fes, symmetric=True)
        a += (2.0 * mu * ng.InnerProduct(eps, ng.Sym(ng.Grad(v))) + lam * ng.Trace(eps) * ng.Trace(ng.Grad(v))) * ng.dx
        f = ng.LinearForm(fes)
        f += -weight * v[1] * ng.dx
        a.Assemble()
        f.Assemble()
        gfu.vec.data = a.mat.Inverse(fes.FreeDofs(), inverse="sparsecholesky") * f.vec
    tip = mesh.Boundaries("tip")
    area = ng.Integrate(ng.CoefficientFunction(1.0), mesh, definedon=tip)
    return -float(ng.Integrate(gfu[1], mesh, definedon=tip)) / area


def _box_mesh(beam: Cantilever, maxh: float):
    """A Netgen mesh of the beam with boundaries named 'clamp' (x = 0) and 'tip' (x = L)."""
    import ngsolve as ng
    from netgen.occ import Box, OCCGeometry, Pnt, X

    box = Box(Pnt(0, 0, 0), Pnt(beam.length, beam.height, beam.width))
    box.faces.Min(X).name = "clamp"
    box.faces.Max(X).name = "tip"
    return ng.Mesh(OCCGeometry(box).GenerateMesh(maxh=maxh))


def converged_sag(
    beam: Cantilever,
    nonlinear: bool = False,
    rtol: float = 1e-4,
    orders: tuple[int, ...] = (2, 3, 4, 5),
    maxh: float | None = None,
    load_steps: int = 4,
) -> ConvergedSag:
    """The sag from NGSolve with increasing polynomial order, stopping when it changes by less than ``rtol``.

    Args:
        beam: The cantilever.
        nonlinear: Solve Saint Venant-Kirchhoff hyperelasticity (large deflection) instead of linear elasticity.
        rtol: Stop once two successive orders differ by less than this relative amount.
        orders: Polynomial orders to try, ascending.
        maxh: Netgen maximum element size (m); default: the beam's smaller cross-section side.
        load_steps: Load increments of the nonlinear Newton solve.

    Returns:
        The study; ``change`` is the last relative change (> ``rtol`` if the orders ran out first).
    """
    if len(orders) < 2:
        raise InputError(f"a convergence study needs at least two orders, got {orders}")
    mesh = _box_mesh(beam, maxh or min(beam.height, beam.width))
    sags: list[float] = []
    for k, order in enumerate(orders):
        sags.append(_solve(mesh, beam, order, nonlinear, load_steps))
        if k and abs(sags[-1] - sags[-2]) < rtol * abs(sags[-1]):
            break
    return ConvergedSag(sags[-1], tuple(orders[: len(sags)]), tuple(sags))


def sag_on_tets(
    beam: Cantilever,
    vertices: np.ndarray,
    tets: np.ndarray,
    nonlinear: bool = False,
    load_steps: int = 4,
    order: int = 1,
) -> float:
    """The sag from NGSolve elements of ``order`` (1: linear tets, as warpfem's) on exactly the given tet mesh.

    Args:
        beam: The cantilever; the mesh must fill its box.
        vertices: (p, 3) vertex positions (m).
        tets: (q, 4) positively oriented tets (as :func:`warpfem.prep.shapes.box_tet_mesh` makes them).
        nonlinear: Saint Venant-Kirchhoff instead of linear elasticity.
        load_steps: Load increments of the nonlinear solve.
        order: Polynomial order (2: quadratic, 10-node tets on the same straight-sided mesh).

    Returns:
        The tip sag (m).
    """
    import ngsolve as ng
    from netgen.meshing import Element2D, Element3D, FaceDescriptor, MeshPoint
    from netgen.meshing import Mesh as NetgenMesh
    from netgen.meshing import Pnt as NetgenPnt

    from warpfem.prep.tetmesh import boundary_faces

    mesh = NetgenMesh(dim=3)
    points = [mesh.Add(MeshPoint(NetgenPnt(*map(float, p)))) for p in vertices]
    for e in np.asarray(tets)[:, [0, 2, 1, 3]]:  # Netgen orients tets the other way round
        mesh.Add(Element3D(1, [points[i] for i in e]))
    names = ("clamp", "tip", "side")
    for k, name in enumerate(names):
        mesh.Add(FaceDescriptor(surfnr=k + 1, domin=1, domout=0, bc=k + 1))
        mesh.SetBCName(k, name)
    faces = boundary_faces(np.asarray(tets))
    x_mean = np.asarray(vertices)[faces, 0].mean(axis=1)
    tol = 1e-6 * beam.length  # QEM leaves a flat face flat to ~5e-8 of the length, not exactly
    for face, x in zip(faces, x_mean, strict=True):
        index = 1 if x < tol else 2 if x > beam.length - tol else 3
        mesh.Add(Element2D(index, [points[i] for i in face]))
    return _solve(ng.Mesh(mesh), beam, order, nonlinear, load_steps)
