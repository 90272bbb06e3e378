"""The reconstructor's output messages for one frame: built here once, published by the
node (rclpy) and written to bags by process_bag (rosbags).

Topics (relative to the node's namespace and name, `~/...`; offline under `--output-ns`):

| key | topic | type | content |
|---|---|---|---|
| segmentation | ~/segmentation | Image rgb8 | part colours |
| labels | ~/segmentation/labels | Image mono8 | part ids (0 background) |
| body_index | ~/bodies/index | Image mono8 | position in ~/bodies/tracked, 255 none |
| mesh | ~/mesh | Marker | one TRIANGLE_LIST per person, ns body_mesh, id = track ID |
| meshes | ~/meshes | MarkerArray | the frame's persons as above, DELETE for IDs gone |
| skeleton | ~/skeleton | MarkerArray | joints (alpha = confidence) and bones, id = track ID |
| smpl_params | ~/smpl_params | JointState | the most central person's parameters |
| bodies_params | ~/bodies/params | JointState | every person's, `body_<id>/` prefixed |
| tracked | ~/bodies/tracked | JointState | body_<id> tracked in the frame |
| tf | /tf | tf2_msgs/TFMessage | body_<id> + <joint>_<id> per person |

The schemas of the JointState topics are in `ros.body_msgs`. Every message carries the
depth image's header (stamp, frame_id); TF frames hang off that frame_id.
"""
from __future__ import annotations

import numpy as np

from smpl_depth_ros.config import OutputOptions
from smpl_depth_ros.ros import adapters as A
from smpl_depth_ros.ros import body_msgs as B
from smpl_depth_ros.ros import markers as M

TF_T = 'tf2_msgs/msg/TFMessage'
# Output key -> (topic: relative, or absolute from '/'; message type), publishing order.
TOPICS = {
    'segmentation': ('segmentation', 'sensor_msgs/msg/Image'),
    'labels': ('segmentation/labels', 'sensor_msgs/msg/Image'),
    'body_index': ('bodies/index', 'sensor_msgs/msg/Image'),
    'mesh': ('mesh', 'visualization_msgs/msg/Marker'),
    'meshes': ('meshes', 'visualization_msgs/msg/MarkerArray'),
    'skeleton': ('skeleton', 'visualization_msgs/msg/MarkerArray'),
    'smpl_params': ('smpl_params', 'sensor_msgs/msg/JointState'),
    'bodies_params': ('bodies/params', 'sensor_msgs/msg/JointState'),
    'tracked': ('bodies/tracked', 'sensor_msgs/msg/JointState'),
    'tf': ('/tf', TF_T),
}


class FrameOutputs:
    """Builds every output message of a frame; remembers the IDs it last published (for
    the DELETE markers of persons who left).

    Args:
        body: the BodyModel; joint_frames: `Fitter.joint_frames` (params -> rotations,
        positions) for TF; opts: OutputOptions; msgs: a MsgFactory (None: rclpy);
        has_tf: whether the tf2_msgs type is available (the node: importable).
    """

    def __init__(self, body, joint_frames, opts: OutputOptions, msgs=None,
                 has_tf: bool = True):
        self.body = body
        self.joint_frames = joint_frames
        self.opts = opts
        self.f = A.as_factory(msgs)
        self.has_tf = has_tf
        jp = body.joint_parents
        self.parents = np.asarray(jp.cpu() if hasattr(jp, 'cpu') else jp).reshape(-1)
        self.joint_names = [str(n) for n in body.joint_names]
        self._faces = (None, None)
        self._last_ids: set[int] = set()

    def forget(self) -> None:
        """Start afresh: no DELETE for earlier IDs (a new bag chunk, a reset)."""
        self._last_ids = set()

    def marker_faces(self) -> np.ndarray:
        frac = float(self.opts.mesh_decimation)
        if self._faces[0] != frac:
            faces = self.body.faces_numpy()
            if frac < 1.0:
                import torch
                with torch.no_grad():
                    rest = self.body(**self.body.zero_params(1)).vertices[0].cpu().numpy()
                faces = M.decimate_faces(rest, faces, max(1, int(round(frac * len(faces)))))
            self._faces = (frac, faces)
        return self._faces[1]

    def build(self, result, persons, header, images: bool = True,
              bodies: bool = True) -> list[tuple[str, object]]:
        """(key, message or its CDR bytes) for the frame, in TOPICS order: the `images`
        (segmentation, labels, body index: they need the finished result's labels and
        masks) and the `bodies` (every other key: meshes, skeleton, parameters, IDs, TF)."""
        f, o = self.f, self.opts
        out = []
        if images and o.publish_segmentation:
            rgb, ids = A.labels_to_image_msgs(result.labels, header, msgs=f)
            out += [('segmentation', rgb), ('labels', ids),
                    ('body_index', A.body_index_image(persons, result.labels.shape, header,
                                                      msgs=f))]
        if bodies:
            out += self._bodies(persons, header)
        return out

    def _bodies(self, persons, header) -> list[tuple[str, object]]:
        f, o = self.f, self.opts
        out = []
        ids = [int(p.track_id) for p in persons]
        gone = sorted(self._last_ids - set(ids))
        self._last_ids = set(ids)
        life = o.mesh_lifetime_s
        if o.publish_mesh:
            faces = self.marker_faces().reshape(-1)
            for p in persons:  # points spliced in as one block (M.marker_cdr)
                empty = M.mesh_marker(np.zeros((0, 3)), np.zeros((0, 3), np.int64), header,
                                      id=p.track_id, lifetime_s=life, msgs=f)
                out.append(('mesh', M.marker_cdr(empty, p.vertices[faces], f)))
            marks = [M.mesh_marker(np.zeros((0, 3)), np.zeros((0, 3), np.int64), header,
                                   id=p.track_id, lifetime_s=life, msgs=f) for p in persons]
            arr = f.new('visualization_msgs/msg/MarkerArray', markers=marks + M.delete_markers(
                [('body_mesh', i) for i in gone], header, msgs=f))
            out.append(('meshes', M.marker_array_cdr(arr, [p.vertices[faces]
                                                           for p in persons], f)))
        if o.publish_skeleton and (persons or gone):
            marks = []
            for p in persons:
                marks += list(M.skeleton_markers(p.joints, self.parents, header, id=p.track_id,
                                                 lifetime_s=life, msgs=f,
                                                 confidence=p.joint_confidence).markers)
            marks += M.delete_markers([(ns, i) for i in gone
                                       for ns in ('skeleton/joints', 'skeleton/bones')],
                                      header, msgs=f)
            out.append(('skeleton', f.new('visualization_msgs/msg/MarkerArray',
                                          markers=marks)))
        if o.publish_params:
            if persons:
                out.append(('smpl_params', B.params_to_joint_state(persons[0], self.body,
                                                                   header, msgs=f)))
            out.append(('bodies_params', B.bodies_to_joint_state(persons, self.body, header,
                                                                 msgs=f)))
            out.append(('tracked', B.tracked_ids_msg(persons, header, msgs=f)))
        if o.publish_tf and self.has_tf and persons:
            tfs = []
            for p in persons:
                R, x = self.joint_frames(p.params)
                tfs += B.body_transforms(p.track_id, R, x, self.parents, self.joint_names,
                                         header, msgs=f)
            out.append(('tf', f.new(TF_T, transforms=tfs)))
        return out
