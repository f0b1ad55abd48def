"""One camera's picture of a model, and what the viewer draws around it, for `boostnerf view`, `render --camera` and
`render --per-expert`; nothing here knows a browser. By job:

- `maps.py`: a mixture's maps (`expert_share`, `gate_probability`, `routing_colours`, the routing `palette`) and the
  depth picture, as `render --per-expert` writes them;
- `frame.py`: what a frame shows (`Look`, one of `MODES`), `picture` and the timed `frame` (`Frame`);
- `camera.py`: the cameras a frame is rendered from: a dataset view's (`dataset_camera`), a browser's
  (`camera_for_view`, from the OpenCV pose `opencv_pose` gives), `fov_of`, `scaled` (the conventions themselves are
  `boostnerf_cli.cameras`);
- `saved.py`: a saved view, a PNG and its camera as JSON (`save_view`, `read_view`) that `render --camera FILE`
  renders again;
- `camera_path.py`: camera paths through keyframes (`CameraPath`), sampled smooth, written and read in nerfstudio's
  camera-path layout (`write_camera_path`, `read_camera_path`) that `render --camera-path FILE` renders and the
  viewer's camera path panel draws;
- `geometry.py`: the scene the viewer draws: the dataset's cameras (`frustums`, `frustum_size`, `hidden_frustums`),
  the box (`box_edges`, `world_box`), the density volume's kept cells coloured by the expert the gate picks there
  (`routed_cells`, in the world: `in_world`); and where it stands first (`subject`, `first_view`, `eye_at`).

A frame's PSNR is `metrics.image.psnr`'s.
"""
