"""Selection, segmentation and editing of a two-view scene, training-free (numpy + scikit-image).

* :mod:`.correspondences`: the encoder's ``matches`` output (each Yin/Yang
  pixel's match in the other reference), stored compactly and read on ERPs;
* :mod:`.segment`: superpixels on colour + inverse range, their region
  graph (colour, depth-edge and normal contrast), prompt selection and the
  automatic multiview-consistent segmentation;
* :mod:`.ops`: which Gaussians a per-view mask owns (through their
  provenance) and the edits (remove, keep, recolor, translate).
"""
