"""Mechanics of the leaflets as energy functions: strain energies (`materials`), the
hinge bending energy (`bending`), the problem's data (`problem`: mesh topology and traced
parameters) and their assembly into energies, forces (autodiff) and the follower pressure
(`assembly`).  Contact laws are in `jaxvalve.contact`.  Units: mm, N, MPa."""
