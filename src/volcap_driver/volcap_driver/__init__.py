"""Cameras for volcap: rosbag2 replay and recording, synthetic 8-camera studio, Azure Kinect import."""
