"""Camera registration with COLMAP (pycolmap, CPU): :mod:`pairs` (which photos to match),
:mod:`database` (COLMAP's database, masks), :mod:`register` (features, matching, incremental
mapping, triangulation at known poses; resumable), :mod:`principal_point` (where the photos put
it), :mod:`model` (a COLMAP reconstruction as a registration)."""
