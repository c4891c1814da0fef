"""Behavior classification from 3D tracks (`deformnet-classify`): tracks and labels
(`tracks`, `labels`, `rates`), the classifier (`encoder`, `heads`, `model`), its features
(`features`), fitting and teaching its head (`fit`, `teachers`, `sequence`), fine-tuning
(`lit`, Lightning), training, prediction and reports (`train`, `predict`: `run(cfg)`,
`report`); the lock box's mechanisms (`lockbox`). Importing the package loads none of them."""
