"""What every stage shares: the capture-folder and EXR file formats, errors, numeric helpers.

This is the one module that stages exchange data through (see ``capture-format.md``); the
pipeline folders (capture, reconstruct, appearance) never import each other.
"""
