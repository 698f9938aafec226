"""glTF 2.0 (the extra ``gltf``: ``pygltflib``): reading skins with their animation, and
writing a rigged animation as one."""
