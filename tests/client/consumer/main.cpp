// Uses the installed kdrt::client: the API compiles and links, proto's codecs are there, and a
// call to a closed port fails as a connection error (no server is needed).

#include <kdrt/client/client.h>
#include <kdrt/proto/ray_batch.h>

#include <cstdio>

int main() {
    kdrt::ClientOptions options;
    options.max_retries = 0;
    kdrt::Client client("http://127.0.0.1:1", options);
    auto health = client.health();
    if (health || health.error().kind != kdrt::ErrorKind::kConnection) {
        std::puts("expected a connection error");
        return 1;
    }
    const std::vector<kdrt::Ray> rays(2, kdrt::Ray{0, 0, 0, 0, 0, 0, 1, 1});
    if (kdrt::proto::encode_rays(rays, false).size() !=
        kdrt::proto::kBatchHeaderBytes + 2 * kdrt::proto::kRayRecordBytes) {
        std::puts("unexpected KDRR size");
        return 1;
    }
    std::printf("consumer ok: %s\n", health.error().to_string().c_str());
    return 0;
}
