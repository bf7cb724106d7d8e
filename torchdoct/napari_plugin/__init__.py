"""The napari plugin of torchdoct (npe2; manifest ``napari.yaml``; install with the ``napari`` extra): one
small module per contribution, each a thin call into the library. docs/napari.md describes it.

* :mod:`.reader`: sequences (intensity in dB over time), maps (one Image layer per channel) and class maps
  (a Labels layer with the legend's colours), every layer scaled in µm;
* :mod:`.writer`: Image layers of maps to ``.ome.tif``, ``.zarr``, ``.npz`` or ``.tif``;
* :mod:`.sample`: the shipped phantoms, rendered on demand;
* :mod:`.widget`: runs ``maps`` (and ``classify`` on the maps) on the open layer, with progress.

The reader and writer import neither napari nor Qt: they are tested through npe2 alone.
"""
