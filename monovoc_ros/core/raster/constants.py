"""The reference rasterizer's constants (graphdeco-inria 3DGS and gsplat), shared by every implementation.

Keeping them identical to what the SLAM front-end renders with is what makes the SCD weights the
weights that produced the map's images.
"""

NEAR_PLANE = 0.2  # metres: Gaussians whose camera-space depth is below this are culled
COV2D_DILATION = 0.3  # added to both diagonal entries of the 2D covariance (low-pass filter, pixels^2)
EIGEN_FLOOR = 0.1  # lambda_max = mid + sqrt(max(EIGEN_FLOOR, mid^2 - det)) as in the CUDA rasterizers
RADIUS_SIGMAS = 3.0  # footprint radius = ceil(RADIUS_SIGMAS * sqrt(lambda_max)) pixels
FOV_MARGIN = 0.3  # the EWA Jacobian is taken at x/z clamped to the image's extent + 0.3 tan(half FoV)
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped (transmittance unchanged)
T_MIN = 1e-4  # a pixel stops once the next transmittance would fall below this, without that blend
TILE = 16  # tile side in pixels; a Gaussian reaches only the pixels of the tiles its radius box touches
DEPTH_MIN_COVERAGE = 1e-6  # depth is left 0 where 1 - T_final is at most this
