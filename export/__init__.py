"""Taking appearance out of damcap: DAMs rendered on new shapes, ONNX and GLSL models, a viewer."""
