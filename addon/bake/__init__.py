"""The baking pipeline on a plain-data scene model (numpy arrays, no bpy).

scene.py (the model), raster.py (texels in UV space), driver.py (the bake), exr.py (EXR I/O)
need no Blender; only extract.py (bpy -> scene model) and apply.py (textures -> images and
material nodes) import bpy.
"""
