"""Camera poses and fusion from image streams (pycolmap SfM, open3d TSDF fusion and ICP).

Not implemented yet: autoalign currently takes calibrated cameras from ``scene_camera.json``.
This subpackage is reserved so that reconstruction lands under ``autoalign.recon``.
"""
