"""Scene loaders: meshes (GLB/glTF, OBJ, PLY), Matterport3D house folders, iGibson scene folders."""
