"""adjust: the geometry half of mousetrack.

Cameras and resection, anipose/DeepLabCut file formats, simulated multi-camera scenes,
triangulation, the pose-track least-squares adjustment and `adjust-track`. May import
`deformnet` (body model, `DeformationModel`); never imports Lightning at import time.
"""
