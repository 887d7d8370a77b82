"""Articulated hands: the procedural model, skinning, poses, glTF import, fitting, scenes.

Modules:
    model     procedural right/left hand on the 25-joint WebXR skeleton (builtin_hand)
    skinning  forward kinematics and LBS (numpy fast path, torch, slow reference)
    poses     named poses, joint limits, random poses, slerp interpolation
    gltf      import of skinned glTF/GLB hands (pygltflib)
    fitting   torch fitting of poses and bone scales to keypoints and scans
    scene     posed meshes of every hand in a scene (world space, with normals)
"""
