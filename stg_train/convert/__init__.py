"""Convert models: compress, quantize, prune, merge, and import / export other tools' files.

Modules (numpy only unless noted; `stg-convert`, stg_train.cli.convert, is the command line over them):

- compress:    prune (faint / unseen Gaussians), Morton-order and quantize a model with presets
               (lossless, balanced, small) and report sizes and the PSNR change
- reference:   import the paper's reference implementation's models (PLY + decoder state dict; the
               decoder needs torch, imported only there)
- gaussians3d: import static 3D Gaussian Splatting PLYs (INRIA layout) and export snapshots as such
- merge:       join files whose segments follow each other
- ply:         a small PLY reader and writer
"""
