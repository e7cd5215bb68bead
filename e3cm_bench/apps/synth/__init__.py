"""Data the package makes itself: procedural textures and the demo pair (textures.py), a
ray-cast non-planar scene (scene.py), and benchmark-layout writers (layouts.py)."""
