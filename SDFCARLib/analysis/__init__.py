"""Quantitative coronary analysis (3D-QCA) of a reconstruction: numpy/scipy/scikit-image only.

Modules (one idea each)
    centreline  skeleton → branches ordered from the ostium, smoothed, with junctions
    section_centreline  each branch moved onto its cross-sections' centroids (the bends smoothing cuts)
    mask_centreline  each branch re-placed on the views' mask midlines (3D-QCA's centreline from the edges)
    mask_order  do the masks belong to their views? the share of the projected centreline on each
    diameter    diameters along a branch: 3D cross-sections of the field, 2D widths in the masks
    frame_contrast  does each frame show its mask's vessels, dark? (an inverted frame is refused)
    frame_widths  2D widths fitted to the frames' intensity profiles (a blurred circular lumen)
    frame_density  lumen area from the frames' absorbance integrated across the vessel (densitometry)
    lesion      robust reference diameter, MLD, % diameter/area stenosis, lesion extent
    fragments   is the reconstruction intact there? pieces analysed, lesions on breaks flagged
    views       foreshortening of a segment in a view, its angle to the views' epipolar planes, best-view map
    phantoms    analytic tubes, helices and stenoses with known answers; exact voxeliser, clean masks
    pipeline    all of the above on one volume (``analyse_volume``) and its JSON summary
    outputs     a result folder → analysis.json, centrelines.vtk, CSV profiles, figures (``analyse``)
    mrml_nodes  the outputs as Slicer nodes: curves with diameters, tables, plots, view map, camera

Not imported here: ``from SDFCARLib.analysis.pipeline import analyse_volume`` etc. keep torch,
vtk and slicer out of a plain import.
"""
