//! Target spacecraft: triangle meshes, materials, procedural targets, OBJ loading, surface sampling.
