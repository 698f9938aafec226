"""USD stages (the extra ``usd``: Pixar's ``pxr``): reading UsdSkel rigs and point caches,
writing rigs, simulated frames and tetrahedral meshes."""
