"""Joint material estimation and segmentation (Maximov et al. 2019, Sec. 3.4).

n deep appearance maps and a segmentation network Psi are trained jointly and unsupervised.
Psi, a small encoder-decoder with skip connections shared among materials, maps a frame's
per-pixel colour, normal and position to soft weights W over the n materials; the weights
enter the data cost of every material (the W of Eq. 3):

    c_d = mean_x sum_k W_k(x) |DAM_k(V(x), N(x)) - L(x)|
    c_s = mean_x (1 - sum_k W_k(x)^2)         (zero when every pixel picks one material)
    cost = c_d + beta c_s

Training starts from k-means clusters of the lit pixels' chromaticity (colour without the amount
of light, so clusters follow materials rather than lit and unlit sides), taken from each surface
point's darkest observation among the training views (specular highlights only add light, and
move with the view), with the illumination's tint modelled as a function of the normal; pixels
too dim to shape the clusters are assigned to the nearest one. Psi is first taught these labels
and each DAM its cluster, then everything is refined jointly. (The paper's k-means baseline,
clusters in RGB + normal space with one DAM fitted per cluster, is :func:`kmeans_baseline`.)

The segmentation is carried onto the geometry: the training pixels' world positions with their
weights form a point set, and any new view (or new shape in the same frame) gets weights by
nearest-neighbour lookup, without ground truth.
"""
