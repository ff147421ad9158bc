"""The MDLShapeModel module's helpers (the module's file keeps its descriptor, parameter node,
Logic, Widget and Test):

- :mod:`.nodes`: between MRML nodes and the library's files;
- :mod:`.jobs`: library work in the background, with progress and Cancel;
- :mod:`.records`: what the Logic returns;
- :mod:`.dependencies`: the Python packages the library needs beyond Slicer's;
- :mod:`.resources`: the module's ``Resources/`` files.
"""
