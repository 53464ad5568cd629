"""sim.collision_mesh.CollisionMesh: one numbering of the collidable vertices for the response, the
penetration checker and the recorder; posing on the host and by the Warp kernel.

Ground truth: the builder's inputs (box corners, rotations written out with cos/sin)."""

import numpy as np
import pytest
import warp as wp

from kernels.pose import VERTEX_BODY, VERTEX_PARTICLE, VERTEX_STATIC
from sim.collision_mesh import CollisionMesh
from sim.builder import ModelBuilder
from sim.mesh_io import box_mesh


def _scene():
    b = ModelBuilder()
    b.add_cloth_grid((0.0, 0.0, 1.0), None, 2, 2, 0.1, 0.1, density=0.1, stretch_stiffness=100.0,
                     shear_stiffness=10.0, bend_stiffness=1.0, damping=0.0)
    b.add_particle((0.5, 0.5, 0.5), mass=0.01)
    verts, tris = box_mesh(0.1)
    angle = 0.7
    b.add_rigid_body(verts, tris, density=100.0, pos=(1.0, 2.0, 3.0),
                     rot=(0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)))
    b.add_static_mesh(verts * 2.0, tris, pos=(0.0, 0.0, -1.0))
    return b.finalize(), verts, tris, angle


def test_numbering_faces_and_host_positions_match_the_builder_inputs():
    model, verts, tris, angle = _scene()
    mesh = CollisionMesh.from_model(model)
    P = 9 + 1
    assert mesh.particle_count == P and mesh.body_count == 1
    assert mesh.shape_offset == P and mesh.static_offset == P + 8 and mesh.vertex_count == P + 16
    assert (mesh.vertex_type[:P] == VERTEX_PARTICLE).all()
    assert (mesh.vertex_type[P:P + 8] == VERTEX_BODY).all() and (mesh.vertex_type[P + 8:] == VERTEX_STATIC).all()
    np.testing.assert_array_equal(mesh.vertex_owner[:P], np.arange(P))
    assert (mesh.vertex_owner[P:] == 0).all()
    T = 8  # 2x2 cells, two triangles each
    assert mesh.face_offsets == (0, T, T + 12, T + 24)
    assert mesh.faces[:T].max() < 9 and (mesh.faces[T:T + 12] >= P).all() and (mesh.faces[T + 12:] >= P + 8).all()
    assert len(mesh.edges) == len({tuple(sorted(e)) for f in mesh.faces for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))})

    x = mesh.positions(model.particle_q.numpy(), model.body_q.numpy())
    np.testing.assert_array_equal(x[:P], model.particle_q.numpy())
    # the box: corners of half extent 0.1 turned by `angle` about z around (1, 2, 3)
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    want_box = (verts - verts.mean(0)) @ rot.T + [1.0, 2.0, 3.0]
    got_box = x[P:P + 8]
    assert np.abs(np.sort(got_box, axis=0) - np.sort(want_box, axis=0)).max() < 1e-12
    np.testing.assert_allclose(np.sort(x[P + 8:], axis=0), np.sort(verts * 2.0 + [0.0, 0.0, -1.0], axis=0), atol=1e-15)


def test_device_pose_equals_host_positions_and_lever_arms():
    model, *_ = _scene()
    mesh = CollisionMesh.from_model(model)
    x = wp.zeros(mesh.vertex_count, dtype=wp.vec3d)
    lever = wp.zeros(mesh.vertex_count, dtype=wp.vec3d)
    mesh.pose(model.particle_q, model.body_q, x, lever)
    host = mesh.positions(model.particle_q.numpy(), model.body_q.numpy())
    np.testing.assert_allclose(x.numpy(), host, atol=1e-14)
    com = model.body_q.numpy()[0, :3]
    np.testing.assert_allclose(lever.numpy()[mesh.shape_offset:mesh.static_offset], host[mesh.shape_offset:mesh.static_offset] - com, atol=1e-14)
    assert (lever.numpy()[: mesh.shape_offset] == 0).all() and (lever.numpy()[mesh.static_offset:] == 0).all()


def test_response_checker_and_recorder_share_one_mesh_numbering(tmp_path):
    from sim.contact.response import ImpulseCollisionHandler
    from sim.penetration import PenetrationChecker
    from sim.recorder import SimRecorder

    model, *_ = _scene()
    state = model.state()
    handler = ImpulseCollisionHandler(model)
    checker = PenetrationChecker(model)
    with SimRecorder(str(tmp_path / "m.rrd"), model) as rec:
        recorder_mesh = rec.mesh
    x_checker = checker.positions(state)
    # the handler poses on the device (the replay's kernel), the checker on the host: the same
    # vertices in the same order, to rounding
    x_handler = handler.detect.pose("start", state.particle_q, state.body_q).numpy()[: handler.n_vertices]
    np.testing.assert_allclose(x_handler, x_checker, rtol=0.0, atol=1e-14)
    np.testing.assert_array_equal(x_handler[: handler.shape_offset], x_checker[: handler.shape_offset])
    for mesh in (handler.mesh, recorder_mesh):
        np.testing.assert_array_equal(mesh.faces, checker.mesh.faces)
        np.testing.assert_array_equal(mesh.vertex_type, checker.mesh.vertex_type)


def test_positions_refuse_states_of_another_model():
    model, *_ = _scene()
    mesh = CollisionMesh.from_model(model)
    with pytest.raises(ValueError, match="particle_q"):
        mesh.positions(np.zeros((3, 3)), model.body_q.numpy())
    with pytest.raises(ValueError, match="body_q"):
        mesh.positions(model.particle_q.numpy(), np.zeros((2, 7)))
