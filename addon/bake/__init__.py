"""The baking pipeline on a plain-data scene model (numpy arrays, no bpy).

scene.py (the model), settings.py, plan.py (which chains), pipeline.py (the bake),
estimators/ (forward-flux, path-points, path-seeded, photon), raster.py (texels in UV space)
and exr.py (EXR I/O) need no Blender; only extract.py (bpy -> scene model) and apply.py
(textures -> images and material nodes) import bpy.  See README.md beside this file.
"""
