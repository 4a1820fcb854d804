"""Render what Foxglove shows for a recording (3D force field, image, net-force plot, status)
with matplotlib, from the Foxglove channels of an MCAP recording (``serve --foxglove
--record``), decoding them the way a viewer does (schemas from the file).

    bubble-rt serve --foxglove 'ws://127.0.0.1:*' --record /tmp/demo.mcap --duration 15
    python3 bench/render_foxglove_view.py /tmp/demo.mcap --out docs/foxglove_view.png

The 3D panel is the frame with the largest estimated net force unless ``--frame`` names a
frame index.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def message_class(name: str, fds_bytes: bytes):  # type: ignore[no-untyped-def]
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(fds_bytes)
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def load(path: str) -> dict:
    from mcap.reader import make_reader

    out: dict = {"scene": [], "image": [], "net": [], "true": [], "status": []}
    classes: dict = {}
    topics = {
        "/bubble_rt/foxglove/scene": "scene",
        "/bubble_rt/foxglove/image": "image",
        "/bubble_rt/foxglove/net_force": "net",
        "/bubble_rt/foxglove/true_force": "true",
        "/bubble_rt/foxglove/status": "status",
    }
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages(topics=list(topics)):
            key = topics[channel.topic]
            if channel.message_encoding == "json":
                out[key].append((message.log_time, json.loads(message.data)))
            else:
                cls = classes.get(schema.name) or message_class(schema.name, schema.data)
                classes[schema.name] = cls
                out[key].append((message.log_time, cls.FromString(message.data)))
    return out


def main() -> int:
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    from scipy.spatial.transform import Rotation

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording")
    ap.add_argument("--out", default="foxglove_view.png")
    ap.add_argument("--frame", type=int, default=None, help="frame index for the 3D panel")
    args = ap.parse_args()
    d = load(args.recording)
    if not d["scene"]:
        print("no /bubble_rt/foxglove/scene in the recording (serve --foxglove --record)")
        return 1
    net = d["net"]

    def n_contact(scene) -> int:  # type: ignore[no-untyped-def]
        return sum(len(e.spheres) for e in scene.entities if e.id == "contact")

    if args.frame is not None:
        k = next(i for i, (_, m) in enumerate(net) if m["frame_index"] == args.frame)
        t_sel = net[k][0]
        scene = min(d["scene"], key=lambda s: abs(s[0] - t_sel))[1]
    else:  # the frame with the most contact nodes (then the largest force)
        mag = {t: m["magnitude"] for t, m in net}
        t_sel, scene = max(d["scene"], key=lambda s: (n_contact(s[1]), mag.get(s[0], 0.0)))
        k = min(range(len(net)), key=lambda i: abs(net[i][0] - t_sel))
    ent = {e.id: e for e in scene.entities}

    fig = plt.figure(figsize=(13, 7.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d", computed_zorder=False)
    tri = ent["membrane"].triangles[0]
    P = np.array([[p.x, p.y, p.z] for p in tri.points]) * 1e3
    C = np.array([[c.r, c.g, c.b, c.a] for c in tri.colors])
    T = np.asarray(tri.indices).reshape(-1, 3)
    poly = Poly3DCollection(
        P[T], facecolors=C[T].mean(axis=1) * [1, 1, 1, 0.8], edgecolors=(0, 0, 0, 0.15), lw=0.3
    )
    ax.add_collection3d(poly)
    for a in ent["forces"].arrows:
        o = a.pose.orientation
        dvec = Rotation.from_quat([o.x, o.y, o.z, o.w]).apply([1.0, 0.0, 0.0])
        L = (a.shaft_length + a.head_length) * 1e3
        p = np.array([a.pose.position.x, a.pose.position.y, a.pose.position.z]) * 1e3
        ax.quiver(*p, *(dvec * L), color="#e0261a", arrow_length_ratio=0.3, lw=1.2, zorder=3)
    sp = ent["contact"].spheres
    if sp:
        S = np.array([[s.pose.position.x, s.pose.position.y, s.pose.position.z] for s in sp])
        ax.scatter(
            *(S.T * 1e3), color="#ffe619", s=14, depthshade=False, edgecolors="k", lw=0.3, zorder=4
        )
    for t in ent["contact"].texts:
        p = t.pose.position
        ax.text(p.x * 1e3, p.y * 1e3, p.z * 1e3 + 4, t.text, color="k", fontsize=9, zorder=5)
    ax.set_xlim(-60, 60)
    ax.set_ylim(-45, 45)
    ax.set_zlim(-20, 45)
    ax.set_box_aspect((120, 90, 65))
    ax.view_init(elev=35, azim=-60)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(
        f"/bubble_rt/foxglove/scene, frame {net[k][1]['frame_index']}\n"
        "colour: normal contact pressure 0 -> 5 kPa; arrows 5 mm per 0.1 N; yellow: contact",
        fontsize=10,
    )

    ax_img = fig.add_subplot(2, 2, 2)
    if d["image"]:
        img_msg = min(d["image"], key=lambda s: abs(s[0] - t_sel))[1]
        bgr = cv2.imdecode(np.frombuffer(img_msg.data, np.uint8), cv2.IMREAD_COLOR)
        ax_img.imshow(bgr[:, :, ::-1])
    ax_img.set_title("/bubble_rt/foxglove/image", fontsize=10)
    ax_img.axis("off")

    ax_p = fig.add_subplot(2, 2, 4)
    t0 = net[0][0]
    tn = np.array([(t - t0) / 1e9 for t, _ in net])
    for comp, col in (("x", "C0"), ("y", "C1"), ("z", "C2")):
        ax_p.plot(tn, [m[comp] for _, m in net], color=col, lw=1.2, label=f"f_{comp}")
    if d["true"]:
        tt = np.array([(t - t0) / 1e9 for t, _ in d["true"]])
        for comp, col in (("x", "C0"), ("y", "C1"), ("z", "C2")):
            ax_p.plot(tt, [m[comp] for _, m in d["true"]], color=col, ls="--", lw=1, alpha=0.8)
        ax_p.plot([], [], "k--", lw=1, label="true (sim)")
    ax_p.axvline((t_sel - t0) / 1e9, color="0.5", lw=0.8)
    ax_p.set_xlabel("time (s)")
    ax_p.set_ylabel("net force (N)")
    ax_p.legend(fontsize=8, ncol=4, loc="lower left")
    ax_p.grid(alpha=0.3)
    st = (d["status"] or [(0, {})])[-1][1]
    ax_p.set_title(
        "/bubble_rt/foxglove/net_force, true_force   "
        f"status: {st.get('state', '?')} {st.get('frame_rate_hz', 0):.1f} Hz, "
        f"p50 {st.get('latency_p50_ms', 0):.0f} ms",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out} (3D panel: frame {net[k][1]['frame_index']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
