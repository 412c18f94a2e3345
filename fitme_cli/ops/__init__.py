"""Small numeric building blocks shared by the shape model and the renderer."""
