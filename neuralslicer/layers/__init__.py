"""Curved layers: isosurfaces of G on the cage (marching tetrahedra), trimmed by H <= 0, in print order."""
from neuralslicer.layers.extract import LayerConfig, Layers, choose_isovalues, extract_layers, slice_layers
from neuralslicer.layers.marching import marching_tets, tet_edges
from neuralslicer.layers.trim import edge_crossings, trim

__all__ = ["LayerConfig", "Layers", "choose_isovalues", "edge_crossings", "extract_layers", "marching_tets",
           "slice_layers", "tet_edges", "trim"]
