"""ament_python build for depth_fusion_ros (also installable with pip)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'depth_fusion_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    package_data={
        PACKAGE: [
            'models/*.pt', 'models/*.yaml', 'config/*.yaml', 'config/*.xml',
            'multiview/*.c', 'multiview/*.h', 'fusion/*.c',
        ]
    },
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml')),
        (f'share/{PACKAGE}/config/cameras', glob('config/cameras/*.yaml')),
        (f'share/{PACKAGE}/launch', glob('launch/*.launch.py')),
    ],
    # ROS packages (rclpy, messages) come from the ROS install or the ros-jazzy-* wheels and
    # torch from its own index (CPU or CUDA build): neither is listed here on purpose.
    install_requires=[
        'setuptools',
        # Ranges, not pins: a library must install beside other packages. The exact versions
        # tested are pinned in scripts/venv.sh.
        'numpy>=2.0',
        'scipy>=1.11',
        'opencv-python-headless>=4.8',
        'rosbags>=0.11,<0.12',  # bag recovery reads rosbags' mcap records (data/bag_recovery.py)
        'pyyaml>=6.0',
        'tqdm>=4.60',
        'matplotlib>=3.7',
    ],
    zip_safe=True,
    maintainer='depth_fusion_ros maintainers',
    maintainer_email='maintainers@depth-fusion-ros.org',
    description='Single-view and multi-view depth fusion for ROS 2 (Facil et al. 2017).',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest>=8']},
    entry_points={
        'console_scripts': [
            'depth-fusion = depth_fusion_ros.cli.main:main',
            'bag_replayer = depth_fusion_ros.nodes.bag_replayer:main',
            'single_view_node = depth_fusion_ros.nodes.single_view_node:main',
            'multi_view_node = depth_fusion_ros.nodes.multi_view_node:main',
            'fusion_node = depth_fusion_ros.nodes.fusion_node:main',
            'map_node = depth_fusion_ros.nodes.map_node:main',
        ],
    },
)
