"""Segment-everything for the objects stage (docs/models/segment-everything.md): MobileSAM's
encoder and decoder runners (mobilesam_runners.py; the torch runtime's: mobilesam_torch.py) and the
generator over them (mobilesam.py), the automatic mask generator's grid, crops, filters and coordinate
maps (amg.py), the prompts it decodes (prompts.py) and those the depth segments give (depth_prompts.py),
the restructured decoder (fast_decoder*.py), reuse across a static camera's frames (reuse.py), and the
weight-free geometric segmenter (geometric.py)."""
