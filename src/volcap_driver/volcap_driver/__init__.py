"""Cameras for volcap: rosbag2 replay and recording, Azure Kinect import."""
