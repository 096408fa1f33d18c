"""Image and geometry algorithms the blocks share; no blocks here.

- edges.py: image derivatives and edges, the directional chamfer tensor, the model contour.
- visibility.py: the hypothesis's rendering and visible model points, cached per frame.
- pose_solver.py: the Levenberg-Marquardt pose solver of the edge-based refiners.
- segmentation.py: the RGB-D scene split into support surfaces and object-like clusters.
- features.py: FPFH model features, correspondence RANSAC, the model distance field.
- colour.py: hue comparison of model and image colours.
- appearance.py: psi_rgb's cues: colour separation across the rendered outline, oriented edge
  agreement, and their search over image-plane shifts.
- verification.py: ICP polishing and render-and-compare verification of hypotheses.
"""
