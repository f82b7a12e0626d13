"""3-vectors, triangle frames and ray-plane crossings, the BVH for shadow rays."""
