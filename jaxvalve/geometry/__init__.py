"""Geometry, the first stage of the data path: the Ozaki leaflet template (`template`), its
triangle mesh (`leaflet_mesh`; `mesh` holds the mesh checks and per-triangle geometry,
`meshgen` the verification meshes), the map of one mesh onto other templates
(`template_map`), the aortic root with its suturing paths (`root`), and the broad phase
of the contact and crossing checks (`broad_phase`).  Lengths in mm."""
