"""ament_python package setup for ooi_seg_ros (also installable with pip)."""

from glob import glob
import os

from setuptools import find_packages, setup

package_name = "ooi_seg_ros"

NODES = ["sfm_node", "segmentation_node", "training_node"]

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "benchmarks"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        (os.path.join("share", package_name, "config"), glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    # optional CUDA rasteriser (JIT-compiles its kernels on first use; needs nvcc + ninja);
    # checked against the CPU rasteriser on an H100 (test/test_raster_gsplat.py)
    extras_require={"gpu": ["gsplat==1.5.3"]},
    zip_safe=True,
    maintainer="ooi_seg_ros maintainers",
    maintainer_email="maintainers@ooi-seg-ros.invalid",
    description="Object-of-interest segmentation and object-only Gaussian splatting for ROS 2",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "ooi-seg = ooi_seg_ros.cli:main",
        ] + [f"{n} = ooi_seg_ros.nodes.{n}:main" for n in NODES],
    },
)
