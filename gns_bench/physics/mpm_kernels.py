"""MLS-MPM substep kernels in Taichi, for 2D and 3D (Hu et al. 2018, "A moving least squares material
point method ...", the paper's reference [15] and the engine DeepMind's MPM domains came from).

One kernel launch is one solver substep: clear grid, particle-to-grid (P2G), grid update, grid-to-particle
(G2P) with the deformation-gradient update and the material's plastic return mapping. Particles live in
Taichi ndarrays so that the kernels compile once per dimension and serve every domain and size.

Materials (all with density 1 in normalised units):
  0 water: weakly compressible fluid, Kirchhoff stress tau = K (J - 1) J I (a linear equation of state);
  1 sand:  Hencky elasticity tau = U (2 mu eps + lambda tr(eps) I) U^T with eps = log Sigma, and the
           Drucker-Prager return mapping of Klar et al. 2016 ("Drucker-Prager elastoplasticity for sand
           animation", eqs. 26-28), cohesionless, friction angle a parameter;
  2 goop:  the same Hencky elasticity with a von Mises yield surface and Bingham-style viscous relaxation
           of the deviatoric strain beyond it (viscoplastic, in the spirit of Yue et al. 2015).
 -1 inactive: a preallocated inflow particle before its birth frame; P2G and G2P skip it (it has no mass
           and does not move) until the solver gives it its material (mpm.MpmRunner.emit).

The grid: nodes at i * dx from the origin, dx = 1 / inv_dx, as many per dimension as the grid arrays hold
(the solver sizes them to cover [0, ceil(upper bound)] of each dimension).

Determinism: P2G scatters with atomic adds. Floating-point adds do not commute, so their result would
depend on thread scheduling; instead each contribution is rounded to a 2^-32 fixed-point integer (mass in
units of one particle's mass, momentum in velocity units) and integer atomic adds commute exactly.
"""


import functools

import taichi as ti

WATER, SAND, GOOP = 0, 1, 2
INACTIVE = -1
FIXED_POINT_SCALE = float(2**32)


@functools.cache
def build_kernels(dim: int):
    """The substep kernel for one dimension (compiled on first call, then shared by every domain)."""
    vec = ti.types.vector(dim, ti.f32)
    mat = ti.types.matrix(dim, dim, ti.f32)
    ivec = ti.types.vector(dim, ti.i64)
    scale = FIXED_POINT_SCALE

    @ti.func
    def stencil(xp, inv_dx, top):
        """The particle's 3^d-node quadratic B-spline stencil: the one place P2G and G2P take their weights from.

        Returns `base`, the stencil's lower corner node, clamped (to `top`, per dimension) so that a runaway
        particle (caught by the solver's per-frame bounds check) can never index outside the grid; `fx`, the
        particle's position relative to `base` in cells (in [0.5, 1.5) unclamped); and `w`, a 3 x dim
        matrix whose row i holds the 1D weights N(fx - i) of node base + i along each dimension, with
        N(r) = 3/4 - r^2 for |r| < 1/2 and (3/2 - |r|)^2 / 2 for 1/2 <= |r| < 3/2.
        """
        base = ti.cast(xp * inv_dx - 0.5, ti.i32)
        for d in ti.static(range(dim)):
            base[d] = ti.min(ti.max(base[d], 0), top[d])
        fx = xp * inv_dx - ti.cast(base, ti.f32)
        w = ti.Matrix.rows([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])
        return base, fx, w

    @ti.func
    def node_weight(w, offset: ti.template()):
        """Weight of node base + offset: the product over dimensions of its 1D weights (rows of `w`)."""
        weight = 1.0
        for d in ti.static(range(dim)):
            weight *= w[offset[d], d]
        return weight

    @ti.func
    def hencky_stress(U, sig, mu, lam):
        """Kirchhoff stress of Hencky (St Venant-Kirchhoff in log strain) elasticity."""
        eps = ti.Vector.zero(ti.f32, dim)
        for d in ti.static(range(dim)):
            eps[d] = ti.log(ti.max(sig[d, d], 1e-4))
        tr = eps.sum()
        diag = ti.Matrix.zero(ti.f32, dim, dim)
        for d in ti.static(range(dim)):
            diag[d, d] = 2.0 * mu * eps[d] + lam * tr
        return U @ diag @ U.transpose()

    @ti.func
    def return_mapping(F, mat_id, mu, lam, alpha, yield_strain, relax):
        """Project the elastic deformation gradient back onto the yield surface; returns F_elastic."""
        U, sig, V = ti.svd(F)
        eps = ti.Vector.zero(ti.f32, dim)
        for d in ti.static(range(dim)):
            eps[d] = ti.log(ti.max(sig[d, d], 1e-4))
        tr = eps.sum()
        dev = eps - tr / dim
        dev_norm = dev.norm() + 1e-12
        if mat_id == SAND:
            if tr >= 0.0:
                eps = ti.Vector.zero(ti.f32, dim)  # expansion: cohesionless grains separate, stress-free
            else:
                # Klar et al. 2016 eq. 27: plastic multiplier of the Drucker-Prager cone
                dgamma = dev_norm + (dim * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
                if dgamma > 0.0:
                    eps = eps - dgamma / dev_norm * dev
        elif mat_id == GOOP:
            excess = dev_norm - yield_strain
            if excess > 0.0:
                # von Mises yield: keep the volumetric part, pull the deviatoric strain towards the
                # yield surface; `relax` in (0, 1] is the implicit Bingham relaxation factor per substep.
                # Implicit Euler of d(excess)/dt = -(2 mu / eta) excess (a Maxwell element beyond yield,
                # Yue et al. 2015 sec. 4 with Herschel-Bulkley exponent 1): in steady flow at deviatoric
                # strain rate D the excess settles at eta D / (2 mu), i.e. ||dev tau|| = yield + eta ||D||,
                # the Bingham law, for any substep (the update is unconditionally stable). The goop's
                # look is set by its parameters (mpm.MaterialParams): eta must damp the impact (low
                # Reynolds number) and yield / (rho g) must stay below a cell, or under-resolved splash
                # sheets freeze into grid-scale spikes.
                new_norm = yield_strain + excess * (1.0 - relax)
                eps = tr / dim + dev * (new_norm / dev_norm)
        new_sig = ti.Matrix.zero(ti.f32, dim, dim)
        for d in ti.static(range(dim)):
            new_sig[d, d] = ti.exp(eps[d])
        return U @ new_sig @ V.transpose(), U, new_sig

    @ti.kernel
    def substep(x: ti.types.ndarray(dtype=vec, ndim=1), v: ti.types.ndarray(dtype=vec, ndim=1),
                C: ti.types.ndarray(dtype=mat, ndim=1), F: ti.types.ndarray(dtype=mat, ndim=1),
                tau: ti.types.ndarray(dtype=mat, ndim=1), material: ti.types.ndarray(dtype=ti.i32, ndim=1),
                grid_p: ti.types.ndarray(dtype=ivec, ndim=dim),
                grid_m: ti.types.ndarray(dtype=ti.i64, ndim=dim),
                grid_v: ti.types.ndarray(dtype=vec, ndim=dim), sdf: ti.types.ndarray(dtype=ti.f32, ndim=dim),
                normal: ti.types.ndarray(dtype=vec, ndim=dim),
                dt: ti.f32, inv_dx: ti.f32, gravity: vec, box_lo: vec, box_hi: vec, box_vel: vec,
                bulk: ti.f32, mu: ti.f32, lam: ti.f32, alpha: ti.f32, yield_strain: ti.f32, relax: ti.f32,
                wall_friction: ti.f32):
        dx = 1.0 / inv_dx
        top = ti.Vector([grid_m.shape[d] - 3 for d in ti.static(range(dim))], ti.i32)
        for g in ti.grouped(grid_m):
            grid_m[g] = 0
            grid_p[g] = ti.Vector.zero(ti.i64, dim)

        # P2G (MLS-MPM eq. 29 of Hu et al. 2018): momentum plus the stress force folded into the affine term
        for p in range(x.shape[0]):
            if material[p] == INACTIVE:
                continue
            base, fx, w = stencil(x[p], inv_dx, top)
            # unit density and unit particle volume/mass ratio: force term -dt * 4/dx^2 * tau
            affine = -dt * 4.0 * inv_dx * inv_dx * tau[p] + C[p]
            for offset in ti.static(ti.grouped(ti.ndrange(*([3] * dim)))):
                dpos = (ti.cast(offset, ti.f32) - fx) * dx
                weight = node_weight(w, offset)
                node = base + offset
                mom = weight * (v[p] + affine @ dpos)
                ti.atomic_add(grid_p[node], ti.cast(ti.round(mom * scale), ti.i64))
                ti.atomic_add(grid_m[node], ti.cast(ti.round(weight * scale), ti.i64))

        # Grid update: momentum to velocity, gravity, then the boundaries
        for g in ti.grouped(grid_m):
            vg = ti.Vector.zero(ti.f32, dim)
            if grid_m[g] > 0:
                m = ti.cast(grid_m[g], ti.f32)
                for d in ti.static(range(dim)):
                    vg[d] = ti.cast(grid_p[g][d], ti.f32) / m
                vg += dt * gravity
                pos = ti.cast(g, ti.f32) * dx
                # container walls (possibly moving): a node within one cell of a wall cannot carry
                # material outward relative to the wall; slip with Coulomb friction tangentially.
                # This is the separating slip condition of Hu et al. 2018's reference code on all sides,
                # the lid included (the data's bounds are the container): only the outward normal
                # velocity is removed, so material that reaches the lid slides along it and falls
                # away under gravity at once (tests/physics: test_water_does_not_stick_to_lid_or_walls)
                for d in ti.static(range(dim)):
                    rel = vg - box_vel
                    vn = 0.0
                    if pos[d] < box_lo[d] + dx and rel[d] < 0.0:
                        vn = rel[d]
                    if pos[d] > box_hi[d] - dx and rel[d] > 0.0:
                        vn = rel[d]
                    if vn != 0.0:
                        rel[d] = 0.0
                        t_norm = rel.norm()
                        if t_norm > 0.0:
                            rel *= ti.max(0.0, 1.0 - wall_friction * ti.abs(vn) / t_norm)
                        vg = rel + box_vel
                # static obstacles, given as a signed distance on the grid (negative inside)
                if sdf[g] < 0.5 * dx:
                    n = normal[g]
                    vn = vg.dot(n)
                    if vn < 0.0:
                        vt = vg - vn * n
                        t_norm = vt.norm()
                        if t_norm > 0.0:
                            vt *= ti.max(0.0, 1.0 - wall_friction * ti.abs(vn) / t_norm)
                        vg = vt
            grid_v[g] = vg

        # G2P: velocity and APIC affine matrix, then F update, plasticity and the next stress
        for p in range(x.shape[0]):
            if material[p] == INACTIVE:
                continue
            base, fx, w = stencil(x[p], inv_dx, top)
            new_v = ti.Vector.zero(ti.f32, dim)
            new_C = ti.Matrix.zero(ti.f32, dim, dim)
            for offset in ti.static(ti.grouped(ti.ndrange(*([3] * dim)))):
                dpos = (ti.cast(offset, ti.f32) - fx) * dx
                weight = node_weight(w, offset)
                g_v = grid_v[base + offset]
                new_v += weight * g_v
                new_C += 4.0 * inv_dx * inv_dx * weight * g_v.outer_product(dpos)
            v[p], C[p] = new_v, new_C
            x[p] += dt * new_v
            F_new = (ti.Matrix.identity(ti.f32, dim) + dt * new_C) @ F[p]
            mat_id = material[p]
            if mat_id == WATER:
                # a fluid keeps only its volume change: F = J^(1/d) I
                J = F_new.determinant()
                F[p] = ti.Matrix.identity(ti.f32, dim) * ti.pow(ti.max(J, 1e-4), 1.0 / dim)
                tau[p] = ti.Matrix.identity(ti.f32, dim) * bulk * (J - 1.0) * J
            else:
                Fe, U, sig = return_mapping(F_new, mat_id, mu, lam, alpha, yield_strain, relax)
                F[p] = Fe
                tau[p] = hencky_stress(U, sig, mu, lam)

    return substep
