# Source me: the environment in which the venv's ROS 2 wheels and the
# workspace's packages are found (AMENT_PREFIX_PATH, PYTHONPATH, ...).
# `. scripts/env.sh --no-workspace` sets up the venv part only (for building).
_artrack_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
_venv=$_artrack_root/.venv
export VIRTUAL_ENV=$_venv
export PATH=$_venv/bin:$PATH
export AMENT_PREFIX_PATH=$_venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}
export CMAKE_PREFIX_PATH=$_venv${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}
export RMW_IMPLEMENTATION=${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}
export PYTHONDONTWRITEBYTECODE=1
if [ "${1:-}" != "--no-workspace" ]; then
  _ins=$_artrack_root/ros2_ws/install
  _pyver=$("$_venv/bin/python" -c 'import sys; print(f"python{sys.version_info[0]}.{sys.version_info[1]}")')
  for _pkg in tf2_msgs hri_msgs artrack_msgs artrack_nodes; do
    [ -d "$_ins/$_pkg" ] || continue  # tf2_msgs / hri_msgs: stand-ins (src/ros_standins)
    export AMENT_PREFIX_PATH=$_ins/$_pkg:$AMENT_PREFIX_PATH
    export PYTHONPATH=$_ins/$_pkg/lib/$_pyver/site-packages${PYTHONPATH:+:$PYTHONPATH}
    export LD_LIBRARY_PATH=$_ins/$_pkg/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
  done
  export PATH=$_ins/artrack_nodes/lib/artrack_nodes:$PATH
fi
# Fast DDS with a shared-memory segment large enough for a frame of camera images
# (config/fastdds.xml says why); a profile the user set is kept.
if [ -z "${FASTRTPS_DEFAULT_PROFILES_FILE:-}" ]; then
  export FASTRTPS_DEFAULT_PROFILES_FILE=$_artrack_root/config/fastdds.xml
fi
unset _artrack_root _venv _ins _pyver _pkg
# Discovery stays on this machine unless the user widens it (two-host runs: SUBNET).
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
export OPENBLAS_NUM_THREADS=${OPENBLAS_NUM_THREADS:-1}
