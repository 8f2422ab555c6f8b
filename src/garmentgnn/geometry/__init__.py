"""Pure, batched tensor mesh operations (no knowledge of bodies, garments or models).

Positions are ``[V, 3]`` or ``[..., V, 3]``; faces one ``[F, 3]`` long tensor shared by
the batch.  Torch functions are differentiable in the positions; the geodesic /
Nystroem functions are numpy/scipy pre-processing on a single rest mesh.
"""
from garmentgnn.geometry.coarsen import coarse_levels, independent_set
from garmentgnn.geometry.distance import (SignedDistance, WindingNumber,
                                          closest_point_on_triangle, push_outside,
                                          signed_distance,
                                          vertex_joint_distances)
from garmentgnn.geometry.penetration import is_closed_mesh, penetration_depth
from garmentgnn.geometry.face_cache import FaceCacheStats, NearestFaceCache
from garmentgnn.geometry.geodesic import (HeatGeodesicSolver, NystromFeatures,
                                          cotan_laplacian, farthest_point_sampling,
                                          geodesic_nystrom_features,
                                          graph_geodesic_distances, heat_geodesic_distances,
                                          mesh_edge_graph, nystrom_eigenvectors)
from garmentgnn.geometry.measures import (angle_defect, angle_defect_difference,
                                          dihedral_angles, edge_lengths, project_edge_lengths,
                                          face_cotangents, gaussian_curvature,
                                          mixed_voronoi_areas)
from garmentgnn.geometry.mesh import (EdgeTopology, FaceAdjacency, boundary_vertex_mask,
                                      edge_features, face_adjacency, faces_to_edge_index,
                                      grid_mesh, unique_edges)
from garmentgnn.geometry.normals import (face_angles, face_areas, face_normals,
                                         scatter_faces_to_vertices, vertex_normals)
from garmentgnn.geometry.precision import full_precision
from garmentgnn.geometry.sdf import plane_distance, sphere_distance
from garmentgnn.geometry.rotations import (axis_angle_to_matrix, euler_to_matrix,
                                           matrix_to_axis_angle, matrix_to_euler,
                                           unwrap_axis_angle)
from garmentgnn.geometry.uv import (DeformationGradient, UVFrame, deformation_gradient,
                                    flat_triangles, uv_deformation_gradient, uv_rest_frame)

__all__ = [
    # mesh connectivity
    "coarse_levels", "independent_set",
    "edge_features", "faces_to_edge_index", "grid_mesh", "unique_edges", "face_adjacency",
    "boundary_vertex_mask", "EdgeTopology", "FaceAdjacency",
    # normals / measures
    "face_normals", "face_areas", "face_angles", "vertex_normals",
    "scatter_faces_to_vertices", "edge_lengths", "project_edge_lengths", "dihedral_angles",
    "face_cotangents",
    "mixed_voronoi_areas", "angle_defect", "angle_defect_difference", "gaussian_curvature",
    # UV deformation gradient (Eq. 14)
    "uv_deformation_gradient", "uv_rest_frame", "deformation_gradient", "flat_triangles",
    "DeformationGradient", "UVFrame",
    # geodesics and Nystroem features (§3.1)
    "mesh_edge_graph", "graph_geodesic_distances", "cotan_laplacian",
    "HeatGeodesicSolver", "heat_geodesic_distances", "farthest_point_sampling",
    "nystrom_eigenvectors", "geodesic_nystrom_features", "NystromFeatures",
    # body distances (Eq. 10)
    "closest_point_on_triangle", "signed_distance", "SignedDistance", "push_outside",
    "vertex_joint_distances", "WindingNumber", "penetration_depth", "is_closed_mesh",
    "NearestFaceCache", "FaceCacheStats",
    # analytic rigid shapes
    "sphere_distance", "plane_distance",
    # rotations
    "axis_angle_to_matrix", "matrix_to_axis_angle", "euler_to_matrix", "matrix_to_euler",
    "unwrap_axis_angle",
    # mixed precision
    "full_precision",
]
