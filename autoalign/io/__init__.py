"""Files: BOP scene folders (``bop``: cameras, masks, labels, photos, depth), models folders
(``models``), instance files and coarse poses (``instances``), atomic writing (``atomic_files``),
the output folder of a run (``out_folder``: created, written all or none, inputs spared),
and the BOP/COCO dataset writer (``export``).

May import: ``geometry``, ``runtime``, ``errors``, and ``rasterizers`` (``export`` renders masks).
"""
