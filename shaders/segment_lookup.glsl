// Segment of a surface point: the manifest's k-d tree, walked on the GPU
// (numpy reference: prt.runtime.manifest.segment_of).  Included after these #defines:
//   PRT_KD_NODES    nodes of the tree (>= 1)
//   PRT_KD_OBJECTS  entries of the root table: object ids 0 .. PRT_KD_OBJECTS - 1 (>= 1)
//   PRT_SEGMENTS    segments (>= 1)

// One node per vec4: inner (axis, split, left, right); leaf (-1, 0, segment, segment).
// Indices and segment ids are exact in float32 (they stay far below 2^24).
uniform vec4 prt_kd_nodes[PRT_KD_NODES];
// Root node of each object id; -1 where the manifest gives the object no root.
uniform int prt_kd_roots[PRT_KD_OBJECTS];
// Segment boxes, the fallback for objects without a root.
uniform vec3 prt_segment_min[PRT_SEGMENTS];
uniform vec3 prt_segment_max[PRT_SEGMENTS];

// Segment whose box is nearest to p (0 inside it; ties go to the lowest id).
int prt_nearest_segment(vec3 p) {
    int best = 0;
    float best_d2 = 3.4e38;
    for (int s = 0; s < PRT_SEGMENTS; ++s) {
        vec3 gap = max(prt_segment_min[s] - p, 0.0) + max(p - prt_segment_max[s], 0.0);
        float d2 = dot(gap, gap);
        if (d2 < best_d2) {
            best = s;
            best_d2 = d2;
        }
    }
    return best;
}

// Segment id of point p on object object_id: descend from the object's root, left when
// p[axis] <= split, to a leaf; objects without a root take the nearest segment box.
int prt_segment(int object_id, vec3 p) {
    int node = (object_id >= 0 && object_id < PRT_KD_OBJECTS) ? prt_kd_roots[object_id] : -1;
    if (node < 0) {
        return prt_nearest_segment(p);
    }
    // A tree is at most PRT_KD_NODES deep; the bound keeps the loop finite on any input.
    for (int depth = 0; depth < PRT_KD_NODES; ++depth) {
        vec4 n = prt_kd_nodes[node];
        int axis = int(n.x);
        if (axis < 0) {
            return int(n.z);
        }
        node = int(p[axis] <= n.y ? n.z : n.w);
    }
    return prt_nearest_segment(p);
}
