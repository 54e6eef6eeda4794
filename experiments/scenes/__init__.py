"""Synthetic scenes and models: ray-cast masks, procedural meshes, an RGB-D stream, the bundled example."""
